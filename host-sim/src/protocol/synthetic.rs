//! Seeded, deterministic synthetic scenes that imitate structure-from-motion models, for
//! training where real data is scarce. A scene is built in four steps:
//!
//! 1. structure: textured surfaces (building boxes, facades, objects, cylinders, ground
//!    planes, hilly terrain), sampled with varied density and clustered like real
//!    detections, each point with a normal and a physical feature size;
//! 2. cameras: on paths or around the structure at varied distances, looking at it, with
//!    intrinsics of every supported COLMAP model (distortion included);
//! 3. detection: a point is seen by a camera when it is in front, inside the image, facing
//!    it, not hidden by a box, and its projected feature size is in the detector's scale
//!    range; each such sighting survives a random dropout. Points detected in at least two
//!    images become 3D points with their tracks;
//! 4. keypoints: every detection as a noisy pixel (triangulated or, for single sightings,
//!    not), plus untriangulated outlier keypoints up to a per-image outlier rate of
//!    30-70 %: detections of unreconstructed texture and image-space clusters (clutter).
//!
//! The output is the same [`Scene`] type as the readers produce.

use std::collections::BTreeMap;
use std::f64::consts::PI;

use gomatch::camera::{CameraModel, MODELS};
use gomatch::{Camera, Pose};
use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;

use crate::protocol::{derive_seed, ProtocolParams};
use crate::scene::{CameraId, Image, ImageId, Keypoint, Point3d, Scene, TrackElement};

/// Candidate structure points per scene before detection dropout.
const POINT_POOL: usize = 40_000;
/// Projected feature sizes (pixels) the simulated detector responds to.
const DETECTABLE_SIZE_PX: (f64, f64) = (2.0, 90.0);
/// Typical projected feature size at the layout's typical viewing distance (pixels).
const TYPICAL_SIZE_PX: f64 = 8.0;
/// Smallest cosine between a surface normal and the direction to the camera (80 degrees).
const MIN_FACING_COS: f64 = 0.17;

/// The kind of place a synthetic scene imitates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// A landmark building on a square, photographed by tourists from scattered spots.
    Landmark,
    /// A street between facades, filmed by a camera moving along it.
    Street,
    /// A small object on a table, photographed on rings around it.
    Object,
    /// Hilly terrain with a few buildings, seen obliquely from a flight path.
    Terrain,
    /// An internet photo collection of a landmark (the paper's MegaDepth setting): photos
    /// from all around it, at very different distances and zooms (telephoto from afar,
    /// wide angle close by), each with its own camera, image size, radial distortion and
    /// keypoint count (300-10,000, mostly untriangulated where there are many). Generated
    /// by [`collection_scene`], outside the mix of [`synthetic_scene`].
    Collection,
}

impl Layout {
    /// The layouts [`synthetic_scene`] draws from.
    const ALL: [Layout; 4] = [
        Layout::Landmark,
        Layout::Street,
        Layout::Object,
        Layout::Terrain,
    ];

    /// Typical camera-to-structure distance (scene units), which sets feature sizes.
    fn typical_distance(self) -> f64 {
        match self {
            Layout::Landmark | Layout::Collection => 40.0,
            Layout::Street => 12.0,
            Layout::Object => 3.5,
            Layout::Terrain => 80.0,
        }
    }
}

/// A parametric surface: `at(s, t)` for `s, t` in `[0, 1]` gives a point and its outward
/// unit normal.
#[derive(Debug, Clone, PartialEq)]
enum Surface {
    /// `origin + s u + t v`; the normal is `u x v`.
    Rectangle {
        origin: Vector3<f64>,
        u: Vector3<f64>,
        v: Vector3<f64>,
    },
    /// Vertical cylinder around `base` (its bottom centre).
    Cylinder {
        base: Vector3<f64>,
        radius: f64,
        height: f64,
    },
    /// Height field `z = sum a sin(kx x + ky y + phase)` over a rectangle of the ground.
    Terrain {
        origin: [f64; 2],
        size: [f64; 2],
        waves: Vec<[f64; 4]>,
    },
}

impl Surface {
    fn at(&self, s: f64, t: f64) -> (Vector3<f64>, Vector3<f64>) {
        match self {
            Surface::Rectangle { origin, u, v } => (origin + u * s + v * t, u.cross(v).normalize()),
            Surface::Cylinder {
                base,
                radius,
                height,
            } => {
                let angle = 2.0 * PI * s;
                let normal = Vector3::new(angle.cos(), angle.sin(), 0.0);
                (
                    base + normal * *radius + Vector3::z() * (height * t),
                    normal,
                )
            }
            Surface::Terrain {
                origin,
                size,
                waves,
            } => {
                let (x, y) = (origin[0] + s * size[0], origin[1] + t * size[1]);
                let (mut z, mut dzdx, mut dzdy) = (0.0, 0.0, 0.0);
                for &[amplitude, kx, ky, phase] in waves {
                    let arg = kx * x + ky * y + phase;
                    z += amplitude * arg.sin();
                    dzdx += amplitude * kx * arg.cos();
                    dzdy += amplitude * ky * arg.cos();
                }
                (
                    Vector3::new(x, y, z),
                    Vector3::new(-dzdx, -dzdy, 1.0).normalize(),
                )
            }
        }
    }

    fn area(&self) -> f64 {
        match self {
            Surface::Rectangle { u, v, .. } => u.cross(v).norm(),
            Surface::Cylinder { radius, height, .. } => 2.0 * PI * radius * height,
            // The slopes add a little area to the footprint.
            Surface::Terrain { size, .. } => 1.1 * size[0] * size[1],
        }
    }
}

/// An oriented box: the building block of structure and the occluder of visibility.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Block {
    centre: Vector3<f64>,
    half: Vector3<f64>,
    yaw: f64,
}

impl Block {
    fn rotation(&self) -> Rotation3<f64> {
        Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw)
    }

    /// The five faces above the ground (no bottom), with outward normals.
    fn faces(&self) -> Vec<Surface> {
        let r = self.rotation();
        let (a, b, h) = (self.half.x, self.half.y, self.half.z);
        let corner = |x: f64, y: f64, z: f64| self.centre + r * Vector3::new(x, y, z);
        let edge = |x: f64, y: f64, z: f64| r * Vector3::new(x, y, z);
        let rect = |origin, u, v| Surface::Rectangle { origin, u, v };
        vec![
            rect(
                corner(a, -b, -h),
                edge(0.0, 2.0 * b, 0.0),
                edge(0.0, 0.0, 2.0 * h),
            ),
            rect(
                corner(-a, -b, -h),
                edge(0.0, 0.0, 2.0 * h),
                edge(0.0, 2.0 * b, 0.0),
            ),
            rect(
                corner(-a, b, -h),
                edge(0.0, 0.0, 2.0 * h),
                edge(2.0 * a, 0.0, 0.0),
            ),
            rect(
                corner(-a, -b, -h),
                edge(2.0 * a, 0.0, 0.0),
                edge(0.0, 0.0, 2.0 * h),
            ),
            rect(
                corner(-a, -b, h),
                edge(2.0 * a, 0.0, 0.0),
                edge(0.0, 2.0 * b, 0.0),
            ),
        ]
    }

    /// Whether the segment from `from` to `to` enters the box before reaching `to` (slab
    /// test in the box frame). A point on the box's own surface does not hide itself.
    fn hides(&self, from: &Vector3<f64>, to: &Vector3<f64>) -> bool {
        let inverse = self.rotation().inverse();
        let origin = inverse * (from - self.centre);
        let direction = inverse * (to - from);
        let (mut t_enter, mut t_exit) = (f64::NEG_INFINITY, f64::INFINITY);
        for axis in 0..3 {
            let (o, d, h) = (origin[axis], direction[axis], self.half[axis]);
            if d.abs() < 1e-15 {
                if o.abs() > h {
                    return false;
                }
                continue;
            }
            let (t0, t1) = ((-h - o) / d, (h - o) / d);
            t_enter = t_enter.max(t0.min(t1));
            t_exit = t_exit.min(t0.max(t1));
        }
        t_exit >= t_enter.max(0.0) && t_enter < 1.0 - 1e-6
    }

    fn contains(&self, p: &Vector3<f64>) -> bool {
        let local = self.rotation().inverse() * (p - self.centre);
        (0..3).all(|axis| local[axis].abs() <= self.half[axis])
    }
}

/// A surface with its relative texture density.
struct Patch {
    surface: Surface,
    density: f64,
}

/// The structure of a scene: textured patches and the boxes that occlude.
struct Structure {
    patches: Vec<Patch>,
    blocks: Vec<Block>,
    /// Point the cameras look around.
    focus: Vector3<f64>,
    /// Rough extent of the interesting structure (for camera placement).
    extent: f64,
}

/// A structure point: position, outward normal and physical feature size.
#[derive(Debug, Clone, Copy)]
struct StructurePoint {
    xyz: Vector3<f64>,
    normal: Vector3<f64>,
    size: f64,
}

/// One simulated camera: intrinsics id and pose.
struct Shot {
    camera_id: CameraId,
    pose: Pose,
}

/// A synthetic scene and the protocol queries drawn from it, as `demo` and `device` take
/// them on the command line.
#[derive(Debug, Clone, clap::Args)]
pub struct SyntheticQueries {
    /// Seed of the synthetic scene family.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Index of the synthetic scene.
    #[arg(long, default_value_t = 0)]
    pub scene: u64,
    /// Queries to localize.
    #[arg(long, default_value_t = 3)]
    pub queries: usize,
    /// Co-visible views per query (image-retrieval stand-in: the protocol's views).
    #[arg(long, default_value_t = 5)]
    pub k: usize,
}

impl SyntheticQueries {
    /// The chosen scene.
    pub fn scene(&self) -> Scene {
        synthetic_scene(self.seed, self.scene)
    }

    /// The protocol drawing the queries, capped at a localizer's `capacity`.
    pub fn protocol(&self, capacity: usize) -> ProtocolParams {
        ProtocolParams::for_localizer(self.k, self.queries, self.seed, capacity)
    }
}

/// Generates synthetic scene number `index` of the family seeded by `seed`, named
/// `synthetic/<index>`. The same `(seed, index)` always gives the same scene.
pub fn synthetic_scene(seed: u64, index: u64) -> Scene {
    let mut rng = Pcg64Mcg::seed_from_u64(derive_seed(seed, &[index]));
    let layout = draw_layout(&mut rng);
    generate(&mut rng, layout, format!("synthetic/{index:04}"))
}

/// The layout of synthetic scene `index` of the family seeded by `seed`.
pub fn synthetic_layout(seed: u64, index: u64) -> Layout {
    draw_layout(&mut Pcg64Mcg::seed_from_u64(derive_seed(seed, &[index])))
}

fn draw_layout(rng: &mut Pcg64Mcg) -> Layout {
    Layout::ALL[rng.random_range(0..Layout::ALL.len())]
}

/// Seed stream of the photo-collection family, apart from [`synthetic_scene`]'s.
const COLLECTION_STREAM: u64 = 0xC011_EC71;

/// Generates photo-collection scene number `index` ([`Layout::Collection`]) of the family
/// seeded by `seed`, named `collection/<index>`. The same `(seed, index)` always gives the
/// same scene; [`synthetic_scene`]'s scenes do not depend on this family.
pub fn collection_scene(seed: u64, index: u64) -> Scene {
    let mut rng = Pcg64Mcg::seed_from_u64(derive_seed(seed, &[index, COLLECTION_STREAM]));
    generate(
        &mut rng,
        Layout::Collection,
        format!("collection/{index:04}"),
    )
}

/// Generates one scene of the given layout from `rng`.
pub fn generate(rng: &mut Pcg64Mcg, layout: Layout, name: String) -> Scene {
    let image_count = rng.random_range(35..=90);
    let structure = build_structure(rng, layout, image_count);
    let points = sample_points(rng, &structure, layout);
    let centres_and_targets = place_cameras(rng, &structure, layout, image_count);
    let (cameras, shots) = if layout == Layout::Collection {
        make_collection_cameras(rng, &structure, &centres_and_targets)
    } else {
        make_cameras(rng, &centres_and_targets)
    };
    let mut scene = Scene {
        name,
        cameras,
        ..Scene::default()
    };
    observe(rng, &mut scene, &structure, &points, &shots, layout);
    scene
}

/// Log-uniform draw in `[low, high]`.
fn log_uniform(rng: &mut Pcg64Mcg, low: f64, high: f64) -> f64 {
    uniform(rng, low.ln(), high.ln()).exp()
}

fn uniform(rng: &mut Pcg64Mcg, low: f64, high: f64) -> f64 {
    low + (high - low) * rng.random::<f64>()
}

fn normal(rng: &mut Pcg64Mcg, sigma: f64) -> f64 {
    sigma * rng.sample::<f64, _>(StandardNormal)
}

fn ground(half_size: f64, density: f64) -> Patch {
    Patch {
        surface: Surface::Rectangle {
            origin: Vector3::new(-half_size, -half_size, 0.0),
            u: Vector3::new(2.0 * half_size, 0.0, 0.0),
            v: Vector3::new(0.0, 2.0 * half_size, 0.0),
        },
        density,
    }
}

fn add_block(structure: &mut Structure, block: Block, density: f64) {
    for surface in block.faces() {
        structure.patches.push(Patch { surface, density });
    }
    structure.blocks.push(block);
}

/// The structure of a layout; a street is as long as `image_count` video frames cover.
fn build_structure(rng: &mut Pcg64Mcg, layout: Layout, image_count: usize) -> Structure {
    let mut s = Structure {
        patches: Vec::new(),
        blocks: Vec::new(),
        focus: Vector3::zeros(),
        extent: 1.0,
    };
    let texture = |rng: &mut Pcg64Mcg| uniform(rng, 0.3, 3.0);
    match layout {
        Layout::Landmark | Layout::Collection => {
            let half = Vector3::new(
                uniform(rng, 10.0, 20.0),
                uniform(rng, 6.0, 12.0),
                uniform(rng, 5.0, 15.0),
            );
            let main = Block {
                centre: Vector3::new(0.0, 0.0, half.z),
                half,
                yaw: 0.0,
            };
            let density = texture(rng);
            add_block(&mut s, main, density);
            for _ in 0..rng.random_range(1..=3) {
                let tower = Vector3::new(
                    uniform(rng, 1.5, 5.0),
                    uniform(rng, 1.5, 5.0),
                    uniform(rng, 3.0, 12.0),
                );
                let x = uniform(rng, -half.x + tower.x, half.x - tower.x);
                let on_top = rng.random_bool(0.5);
                let centre = if on_top {
                    Vector3::new(x, uniform(rng, -0.5, 0.5) * half.y, 2.0 * half.z + tower.z)
                } else {
                    Vector3::new(x, half.y + tower.y, tower.z)
                };
                let density = texture(rng);
                add_block(
                    &mut s,
                    Block {
                        centre,
                        half: tower,
                        yaw: 0.0,
                    },
                    density,
                );
            }
            if rng.random_bool(0.5) {
                let radius = uniform(rng, 0.5, 2.0);
                s.patches.push(Patch {
                    surface: Surface::Cylinder {
                        base: Vector3::new(uniform(rng, -10.0, 10.0), half.y + 12.0, 0.0),
                        radius,
                        height: uniform(rng, 3.0, 10.0),
                    },
                    density: texture(rng),
                });
            }
            s.patches.push(ground(70.0, uniform(rng, 0.05, 0.4)));
            s.focus = Vector3::new(0.0, 0.0, half.z);
            s.extent = half.x.max(half.y);
        }
        Layout::Street => {
            let width = uniform(rng, 5.0, 9.0);
            let length = image_count as f64 * uniform(rng, 0.5, 1.5);
            for side in [-1.0, 1.0] {
                let mut x = -10.0;
                while x < length + 10.0 {
                    let w = uniform(rng, 4.0, 10.0);
                    let half = Vector3::new(w, 6.0, uniform(rng, 4.0, 13.0));
                    let setback = uniform(rng, 0.0, 1.5);
                    let block = Block {
                        centre: Vector3::new(x + w, side * (width + setback + half.y), half.z),
                        half,
                        yaw: 0.0,
                    };
                    let density = texture(rng);
                    add_block(&mut s, block, density);
                    x += 2.0 * w + uniform(rng, 0.0, 3.0);
                }
            }
            s.patches.push(Patch {
                surface: Surface::Rectangle {
                    origin: Vector3::new(-15.0, -width - 2.0, 0.0),
                    u: Vector3::new(length + 30.0, 0.0, 0.0),
                    v: Vector3::new(0.0, 2.0 * width + 4.0, 0.0),
                },
                density: uniform(rng, 0.1, 0.8),
            });
            s.focus = Vector3::new(length, 0.0, 1.6);
            s.extent = width;
        }
        Layout::Object => {
            let half = Vector3::new(
                uniform(rng, 0.3, 0.8),
                uniform(rng, 0.2, 0.6),
                uniform(rng, 0.15, 0.5),
            );
            let main = Block {
                centre: Vector3::new(0.0, 0.0, half.z),
                half,
                yaw: uniform(rng, 0.0, PI),
            };
            let density = texture(rng) * 200.0;
            add_block(&mut s, main, density);
            for _ in 0..rng.random_range(0..=2) {
                let small = Vector3::new(
                    uniform(rng, 0.1, 0.3),
                    uniform(rng, 0.1, 0.3),
                    uniform(rng, 0.05, 0.3),
                );
                let angle = uniform(rng, 0.0, 2.0 * PI);
                let distance = uniform(rng, 1.0, 1.6) * half.x.max(half.y) + small.x;
                let density = texture(rng) * 200.0;
                add_block(
                    &mut s,
                    Block {
                        centre: Vector3::new(
                            distance * angle.cos(),
                            distance * angle.sin(),
                            small.z,
                        ),
                        half: small,
                        yaw: uniform(rng, 0.0, PI),
                    },
                    density,
                );
            }
            if rng.random_bool(0.6) {
                let angle = uniform(rng, 0.0, 2.0 * PI);
                s.patches.push(Patch {
                    surface: Surface::Cylinder {
                        base: Vector3::new(1.2 * angle.cos(), 1.2 * angle.sin(), 0.0),
                        radius: uniform(rng, 0.05, 0.25),
                        height: uniform(rng, 0.2, 0.8),
                    },
                    density: texture(rng) * 200.0,
                });
            }
            s.patches.push(ground(3.0, uniform(rng, 5.0, 60.0)));
            s.focus = Vector3::new(0.0, 0.0, half.z);
            s.extent = half.x.max(half.y);
        }
        Layout::Terrain => {
            let waves = (0..4)
                .map(|_| {
                    let wavelength = uniform(rng, 40.0, 200.0);
                    let direction = uniform(rng, 0.0, 2.0 * PI);
                    let k = 2.0 * PI / wavelength;
                    [
                        uniform(rng, 1.0, 6.0),
                        k * direction.cos(),
                        k * direction.sin(),
                        uniform(rng, 0.0, 2.0 * PI),
                    ]
                })
                .collect();
            s.patches.push(Patch {
                surface: Surface::Terrain {
                    origin: [-150.0, -150.0],
                    size: [300.0, 300.0],
                    waves,
                },
                density: 1.0,
            });
            for _ in 0..rng.random_range(4..=10) {
                let half = Vector3::new(
                    uniform(rng, 3.0, 10.0),
                    uniform(rng, 3.0, 10.0),
                    uniform(rng, 3.0, 10.0),
                );
                let block = Block {
                    centre: Vector3::new(
                        uniform(rng, -100.0, 100.0),
                        uniform(rng, -100.0, 100.0),
                        half.z,
                    ),
                    half,
                    yaw: uniform(rng, 0.0, PI),
                };
                let density = texture(rng) * 2.0;
                add_block(&mut s, block, density);
            }
            s.extent = 100.0;
        }
    }
    s
}

/// Samples the structure: points spread over the patches by area times density, a share of
/// each patch's points in texture clusters, each with a log-normal feature size.
fn sample_points(rng: &mut Pcg64Mcg, structure: &Structure, layout: Layout) -> Vec<StructurePoint> {
    let weights: Vec<f64> = structure
        .patches
        .iter()
        .map(|p| p.surface.area() * p.density)
        .collect();
    let total: f64 = weights.iter().sum();
    let median_size = TYPICAL_SIZE_PX * layout.typical_distance() / 1000.0;
    let mut points = Vec::with_capacity(POINT_POOL);
    for (patch, weight) in structure.patches.iter().zip(&weights) {
        let count = (POINT_POOL as f64 * weight / total).round() as usize;
        let clustered = (count as f64 * uniform(rng, 0.4, 0.8)) as usize;
        let cluster_count = (clustered / rng.random_range(15..60)).max(1);
        let centres: Vec<[f64; 3]> = (0..cluster_count)
            .map(|_| [rng.random(), rng.random(), uniform(rng, 0.005, 0.04)])
            .collect();
        for i in 0..count {
            let (s, t) = if i < clustered {
                let [cs, ct, sigma] = centres[rng.random_range(0..centres.len())];
                (
                    (cs + normal(rng, sigma)).clamp(0.0, 1.0),
                    (ct + normal(rng, sigma)).clamp(0.0, 1.0),
                )
            } else {
                (rng.random(), rng.random())
            };
            let (xyz, normal_vector) = patch.surface.at(s, t);
            let size = median_size * normal(rng, 0.7).exp();
            points.push(StructurePoint {
                xyz,
                normal: normal_vector,
                size,
            });
        }
    }
    points
}

/// Camera centres and look-at targets for the layout.
fn place_cameras(
    rng: &mut Pcg64Mcg,
    structure: &Structure,
    layout: Layout,
    count: usize,
) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let mut shots = Vec::with_capacity(count);
    let inside_block = |c: &Vector3<f64>| structure.blocks.iter().any(|b| b.contains(c));
    match layout {
        Layout::Landmark => {
            let spots: Vec<(f64, f64)> = (0..rng.random_range(3..=6))
                .map(|_| {
                    (
                        PI / 2.0 + uniform(rng, -1.9, 1.9),
                        structure.extent * uniform(rng, 1.4, 4.0),
                    )
                })
                .collect();
            while shots.len() < count {
                let (angle, distance) = spots[rng.random_range(0..spots.len())];
                let angle = angle + normal(rng, 0.12);
                let distance = distance * (1.0 + normal(rng, 0.15)).max(0.5);
                let height = if rng.random_bool(0.1) {
                    uniform(rng, 5.0, 25.0)
                } else {
                    uniform(rng, 1.4, 2.0)
                };
                let centre = Vector3::new(distance * angle.cos(), distance * angle.sin(), height);
                let target = structure.focus
                    + Vector3::new(
                        normal(rng, structure.extent * 0.3),
                        0.0,
                        normal(rng, structure.focus.z * 0.4),
                    );
                if !inside_block(&centre) {
                    shots.push((centre, target));
                }
            }
        }
        Layout::Street => {
            let length = structure.focus.x;
            let sideways = rng.random_bool(0.3);
            for i in 0..count {
                let x = length * i as f64 / count as f64 + normal(rng, 0.3);
                let centre = Vector3::new(x, normal(rng, 0.5), 1.6 + normal(rng, 0.05));
                // Sideways runs look at one side of the street for 15 frames, then the other.
                let yaw = match (sideways, (i / 15) % 2) {
                    (false, _) => 0.0,
                    (true, 0) => PI / 2.0,
                    (true, _) => -PI / 2.0,
                } + normal(rng, 0.25);
                let direction = Vector3::new(yaw.cos(), yaw.sin(), normal(rng, 0.05));
                shots.push((centre, centre + direction * 10.0));
            }
        }
        Layout::Object => {
            let rings = rng.random_range(1..=3);
            while shots.len() < count {
                let ring = shots.len() % rings;
                let distance = structure.extent * uniform(rng, 2.5, 6.0) + 0.3 * ring as f64;
                let angle =
                    2.0 * PI * shots.len() as f64 / count as f64 * rings as f64 + normal(rng, 0.05);
                let height = uniform(rng, 0.3, 2.5) * structure.extent.max(0.3) + 0.3 * ring as f64;
                let centre = Vector3::new(distance * angle.cos(), distance * angle.sin(), height);
                let target = structure.focus
                    + Vector3::new(normal(rng, 0.1), normal(rng, 0.1), normal(rng, 0.05));
                if !inside_block(&centre) {
                    shots.push((centre, target));
                }
            }
        }
        Layout::Collection => {
            while shots.len() < count {
                // Anywhere on the accessible side, at any distance: wide baselines.
                let angle = PI / 2.0 + uniform(rng, -2.6, 2.6);
                let distance = structure.extent * log_uniform(rng, 1.3, 6.0);
                let height = if rng.random_bool(0.15) {
                    uniform(rng, 5.0, 40.0)
                } else {
                    uniform(rng, 1.4, 2.0)
                };
                let centre = Vector3::new(distance * angle.cos(), distance * angle.sin(), height);
                // Close-ups frame a part of the building, distant shots its middle.
                let spread = structure.extent * (0.6 - 0.4 * (distance / structure.extent / 6.0));
                let target = structure.focus
                    + Vector3::new(
                        normal(rng, spread),
                        normal(rng, 0.3 * spread),
                        normal(rng, structure.focus.z * 0.4),
                    );
                if !inside_block(&centre) {
                    shots.push((centre, target));
                }
            }
        }
        Layout::Terrain => {
            let radius = uniform(rng, 40.0, 90.0);
            let altitude = uniform(rng, 45.0, 80.0);
            let pitch = uniform(rng, 0.6, 1.2);
            for i in 0..count {
                let angle = 2.0 * PI * i as f64 / count as f64;
                let centre = Vector3::new(
                    radius * angle.cos(),
                    radius * angle.sin(),
                    altitude + normal(rng, 1.0),
                );
                // Heading along the loop, tilted down by `pitch`.
                let heading = angle + PI / 2.0 + normal(rng, 0.1);
                let direction = Vector3::new(
                    heading.cos() * pitch.cos(),
                    heading.sin() * pitch.cos(),
                    -pitch.sin(),
                );
                shots.push((centre, centre + direction * 10.0));
            }
        }
    }
    shots
}

/// World-to-camera pose of a camera at `centre` looking at `target` (z up in the world),
/// rolled by `roll` radians: rows of `R` are the camera's right, down and forward axes.
pub fn look_at(centre: &Vector3<f64>, target: &Vector3<f64>, roll: f64) -> Pose {
    let forward = (target - centre).normalize();
    let up = if forward.cross(&Vector3::z()).norm() < 1e-6 {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let right = forward.cross(&up).normalize();
    let down = forward.cross(&right);
    let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
    let rolled =
        Rotation3::from_axis_angle(&Vector3::z_axis(), roll) * Rotation3::from_matrix_unchecked(r);
    Pose::new(rolled, -(rolled * centre))
}

/// Intrinsics for the images: one shared camera or one per image (as in the real models),
/// of a random COLMAP model and image size.
fn make_cameras(
    rng: &mut Pcg64Mcg,
    centres_and_targets: &[(Vector3<f64>, Vector3<f64>)],
) -> (BTreeMap<CameraId, Camera>, Vec<Shot>) {
    const SIZES: [(u32, u32); 6] = [
        (640, 480),
        (802, 658),
        (1024, 768),
        (1280, 720),
        (1600, 1200),
        (1920, 1080),
    ];
    let model = MODELS[rng.random_range(0..MODELS.len())].model;
    let (mut width, mut height) = SIZES[rng.random_range(0..SIZES.len())];
    if rng.random_bool(0.2) {
        std::mem::swap(&mut width, &mut height);
    }
    let shared = rng.random_bool(0.5);
    let base_fov = uniform(rng, 45.0, 75.0).to_radians();
    let mut cameras = BTreeMap::new();
    let mut shots = Vec::with_capacity(centres_and_targets.len());
    for (i, (centre, target)) in centres_and_targets.iter().enumerate() {
        let camera_id = if shared { 1 } else { i as CameraId + 1 };
        cameras.entry(camera_id).or_insert_with(|| {
            let fov = base_fov * if shared { 1.0 } else { uniform(rng, 0.8, 1.2) };
            random_intrinsics(rng, model, width, height, fov)
        });
        let roll = normal(rng, 0.04);
        shots.push(Shot {
            camera_id,
            pose: look_at(centre, target, roll),
        });
    }
    (cameras, shots)
}

/// Image sizes of a photo collection (landscape; a quarter of the photos are portrait).
const COLLECTION_SIZES: [(u32, u32); 9] = [
    (640, 480),
    (800, 600),
    (1024, 768),
    (1280, 720),
    (1600, 1200),
    (1920, 1080),
    (2048, 1365),
    (3000, 2000),
    (4000, 3000),
];
/// Horizontal field of view range of a photo collection (degrees).
const COLLECTION_FOV_DEG: (f64, f64) = (10.0, 130.0);

/// One camera per photo of a collection: a random size; a zoom that frames the building
/// from where the photo was taken (telephoto from afar, wide angle close by; a fifth of
/// the photos zoom at random); a simple radial lens whose barrel or pincushion distortion
/// at the image corner is weak (|d| <= 1 %) for 60 % of the photos and strong (-25 % to
/// +8 %) for the others.
fn make_collection_cameras(
    rng: &mut Pcg64Mcg,
    structure: &Structure,
    centres_and_targets: &[(Vector3<f64>, Vector3<f64>)],
) -> (BTreeMap<CameraId, Camera>, Vec<Shot>) {
    let mut cameras = BTreeMap::new();
    let mut shots = Vec::with_capacity(centres_and_targets.len());
    let (min_fov, max_fov) = COLLECTION_FOV_DEG;
    for (i, (centre, target)) in centres_and_targets.iter().enumerate() {
        let camera_id = i as CameraId + 1;
        let (mut width, mut height) = COLLECTION_SIZES[rng.random_range(0..COLLECTION_SIZES.len())];
        if rng.random_bool(0.25) {
            std::mem::swap(&mut width, &mut height);
        }
        let distance = (target - centre).norm();
        let framed = 2.0 * (structure.extent * uniform(rng, 0.4, 1.5) / distance).atan();
        let fov_deg = if rng.random_bool(0.2) {
            log_uniform(rng, min_fov, max_fov)
        } else {
            (framed.to_degrees() * uniform(rng, 1.0, 2.5)).clamp(min_fov, max_fov)
        };
        let (w, h) = (f64::from(width), f64::from(height));
        let f = 0.5 * w / (0.5 * fov_deg.to_radians()).tan();
        let corner_radius = (0.5 * w).hypot(0.5 * h) / f;
        let corner_distortion = if rng.random_bool(0.6) {
            uniform(rng, -0.01, 0.01)
        } else {
            uniform(rng, -0.25, 0.08)
        };
        let k1 = corner_distortion / (corner_radius * corner_radius);
        let cx = 0.5 * w + normal(rng, 0.01 * w);
        let cy = 0.5 * h + normal(rng, 0.01 * h);
        let camera =
            Camera::from_colmap(CameraModel::SimpleRadial, width, height, &[f, cx, cy, k1])
                .expect("collection intrinsics are finite with a positive focal length");
        cameras.insert(camera_id, camera);
        shots.push(Shot {
            camera_id,
            pose: look_at(centre, target, normal(rng, 0.04)),
        });
    }
    (cameras, shots)
}

fn random_intrinsics(
    rng: &mut Pcg64Mcg,
    model: CameraModel,
    width: u32,
    height: u32,
    horizontal_fov: f64,
) -> Camera {
    let (w, h) = (f64::from(width), f64::from(height));
    let f = 0.5 * w / (0.5 * horizontal_fov).tan();
    let fy = f * (1.0 + normal(rng, 0.005));
    let cx = 0.5 * w + normal(rng, 0.01 * w);
    let cy = 0.5 * h + normal(rng, 0.01 * h);
    let k1 = uniform(rng, -0.12, 0.05);
    let k2 = uniform(rng, -0.02, 0.02);
    let (p1, p2) = (normal(rng, 5e-4), normal(rng, 5e-4));
    // Every intrinsic drawn, then the model keeps its own parameters of them.
    let (params, count) = Camera {
        model,
        width,
        height,
        focal: [f, fy],
        principal: [cx, cy],
        distortion: [k1, k2, p1, p2],
    }
    .colmap_params();
    Camera::from_colmap(model, width, height, &params[..count])
        .expect("synthetic intrinsics are finite with a positive focal length")
}

/// Largest bearing radius inside the image: beyond it the distortion polynomial is not
/// trusted to be invertible.
fn max_bearing_radius(camera: &Camera) -> f64 {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]
        .iter()
        .filter_map(|&corner| camera.pixel_to_bearing(corner).ok())
        .map(|b| (b[0] * b[0] + b[1] * b[1]).sqrt())
        .fold(0.0, f64::max)
        * 1.05
}

/// Pixel of a point in a shot, when the point is detectable there: in front, within the
/// image, facing the camera, not hidden by a box, at a detectable scale. Also returns the
/// facing cosine.
fn sighting(
    camera: &Camera,
    max_radius: f64,
    pose: &Pose,
    centre: &Vector3<f64>,
    point: &StructurePoint,
    blocks: &[Block],
) -> Option<([f64; 2], f64)> {
    let to_camera = centre - point.xyz;
    let distance = to_camera.norm();
    let facing = point.normal.dot(&to_camera) / distance;
    if facing < MIN_FACING_COS {
        return None;
    }
    let depth = pose.transform(&point.xyz).z;
    let projected_size = camera.mean_focal() * point.size / depth.max(1e-9);
    if !(DETECTABLE_SIZE_PX.0..=DETECTABLE_SIZE_PX.1).contains(&projected_size) {
        return None;
    }
    let bearing = pose.bearing(&point.xyz, 0).ok()?;
    if bearing[0].hypot(bearing[1]) > max_radius {
        return None;
    }
    let pixel = camera.bearing_to_pixel(bearing).ok()?;
    let inside = pixel[0] >= 0.0
        && pixel[1] >= 0.0
        && pixel[0] < f64::from(camera.width)
        && pixel[1] < f64::from(camera.height);
    if !inside || blocks.iter().any(|b| b.hides(centre, &point.xyz)) {
        return None;
    }
    Some((pixel, facing))
}

/// Detection, tracks and keypoints (steps 3 and 4 of the module documentation).
fn observe(
    rng: &mut Pcg64Mcg,
    scene: &mut Scene,
    structure: &Structure,
    points: &[StructurePoint],
    shots: &[Shot],
    layout: Layout,
) {
    let noise_px = uniform(rng, 0.35, 0.9);
    let target_keypoints = uniform(rng, 300.0, 1500.0);
    let mean_outlier_rate = uniform(rng, 0.35, 0.65);
    let max_radii: Vec<f64> = shots
        .iter()
        .map(|s| max_bearing_radius(&scene.cameras[&s.camera_id]))
        .collect();
    // Geometric sightings per shot: (point index, pixel, facing cosine).
    let sightings: Vec<Vec<(usize, [f64; 2], f64)>> = shots
        .iter()
        .zip(&max_radii)
        .map(|(shot, &max_radius)| {
            let camera = &scene.cameras[&shot.camera_id];
            let centre = shot.pose.center();
            points
                .iter()
                .enumerate()
                .filter_map(|(i, p)| {
                    sighting(
                        camera,
                        max_radius,
                        &shot.pose,
                        &centre,
                        p,
                        &structure.blocks,
                    )
                    .map(|(pixel, facing)| (i, pixel, facing))
                })
                .collect()
        })
        .collect();
    // Detection is mostly a property of the point (a salient corner is found in every view
    // that sees it at a suitable scale), so a random subset of points is active, and each
    // sighting of an active point is detected with the detector's repeatability, lower at
    // grazing angles. The active share brings the detections near the target count.
    let repeatability = uniform(rng, 0.7, 0.95);
    let detection_probability =
        |facing: f64| repeatability * ((facing - MIN_FACING_COS) / 0.4).clamp(0.2, 1.0);
    let expected_per_image = sightings
        .iter()
        .flatten()
        .map(|&(_, _, facing)| detection_probability(facing))
        .sum::<f64>()
        / shots.len().max(1) as f64;
    let target_detections = target_keypoints * (1.0 - mean_outlier_rate);
    let active_share = (target_detections / expected_per_image.max(1.0)).min(1.0);
    let active: Vec<bool> = (0..points.len())
        .map(|_| rng.random_bool(active_share))
        .collect();
    let detections: Vec<Vec<(usize, [f64; 2])>> = sightings
        .into_iter()
        .map(|list| {
            list.into_iter()
                .filter(|&(i, _, facing)| {
                    active[i] && rng.random_bool(detection_probability(facing))
                })
                .map(|(i, pixel, _)| (i, pixel))
                .collect()
        })
        .collect();
    let mut seen_by = vec![0u32; points.len()];
    for list in &detections {
        for &(i, _) in list {
            seen_by[i] += 1;
        }
    }
    // Points detected twice or more are triangulated, with ids in structure order.
    let mut point_ids = vec![None; points.len()];
    let mut next_id = 1u64;
    for (i, &count) in seen_by.iter().enumerate() {
        if count >= 2 {
            point_ids[i] = Some(next_id);
            scene.points.insert(
                next_id,
                Point3d {
                    id: next_id,
                    xyz: points[i].xyz,
                    track: Vec::new(),
                },
            );
            next_id += 1;
        }
    }
    for (index, (shot, list)) in shots.iter().zip(&detections).enumerate() {
        let image_id = index as ImageId + 1;
        let camera = scene.cameras[&shot.camera_id];
        let mut keypoints: Vec<Keypoint> = list
            .iter()
            .map(|&(i, pixel)| Keypoint {
                pixel: [
                    pixel[0] + normal(rng, noise_px),
                    pixel[1] + normal(rng, noise_px),
                ],
                point3d: point_ids[i],
            })
            .collect();
        let triangulated = keypoints.iter().filter(|k| k.point3d.is_some()).count();
        let rate = if layout == Layout::Collection {
            collection_outlier_rate(rng, triangulated)
        } else {
            (mean_outlier_rate + normal(rng, 0.08)).clamp(0.3, 0.7)
        };
        let wanted_outliers = (triangulated as f64 * rate / (1.0 - rate)).round() as usize;
        let missing = wanted_outliers.saturating_sub(keypoints.len() - triangulated);
        let texture_share = uniform(rng, 0.3, 0.7);
        let texture = (missing as f64 * texture_share).round() as usize;
        keypoints.extend(unreconstructed_texture(
            rng,
            structure,
            points,
            &camera,
            shot,
            max_radii[index],
            texture,
            noise_px,
        ));
        keypoints.extend(clutter(rng, &camera, missing - texture.min(missing)));
        keypoints.shuffle(rng);
        for (k, keypoint) in keypoints.iter().enumerate() {
            if let Some(id) = keypoint.point3d {
                if let Some(point) = scene.points.get_mut(&id) {
                    point.track.push(TrackElement {
                        image_id,
                        keypoint_index: k as u32,
                    });
                }
            }
        }
        scene.images.insert(
            image_id,
            Image {
                id: image_id,
                name: format!("{image_id:05}.jpg"),
                camera_id: shot.camera_id,
                pose: shot.pose,
                keypoints,
            },
        );
    }
}

/// Keypoints per photo of a collection: `low (high / low)^(u^2)` for a uniform `u`, a
/// log-scale skewed towards few (quartiles about 370 / 720 / 2,200, as the real training
/// scenes' 380 / 530 / 1,040 with a longer tail). A photo's resolution and texture set its
/// keypoint count, while what gets triangulated depends on the other photos, so the
/// untriangulated share grows with the count (15-95 %).
const COLLECTION_KEYPOINTS: (f64, f64) = (300.0, 10_000.0);

/// Outlier rate of a collection photo with `triangulated` keypoints: what fills it up to
/// its drawn keypoint count.
fn collection_outlier_rate(rng: &mut Pcg64Mcg, triangulated: usize) -> f64 {
    let (low, high) = COLLECTION_KEYPOINTS;
    let keypoints = low * (high / low).powf(rng.random::<f64>().powi(2));
    (1.0 - triangulated as f64 / keypoints).clamp(0.15, 0.95)
}

/// Untriangulated detections of texture that the model never reconstructed: random
/// structure points, re-sampled near their cluster, that the shot can see.
#[allow(clippy::too_many_arguments)]
fn unreconstructed_texture(
    rng: &mut Pcg64Mcg,
    structure: &Structure,
    points: &[StructurePoint],
    camera: &Camera,
    shot: &Shot,
    max_radius: f64,
    count: usize,
    noise_px: f64,
) -> Vec<Keypoint> {
    let centre = shot.pose.center();
    let mut keypoints = Vec::with_capacity(count);
    // Bounded attempts: a shot that sees little structure gets fewer such outliers.
    for _ in 0..count * 20 {
        if keypoints.len() == count {
            break;
        }
        let anchor = points[rng.random_range(0..points.len())];
        let offset = Vector3::new(normal(rng, 1.0), normal(rng, 1.0), normal(rng, 1.0))
            * (3.0 * anchor.size);
        let offset = offset - anchor.normal * anchor.normal.dot(&offset);
        let candidate = StructurePoint {
            xyz: anchor.xyz + offset,
            ..anchor
        };
        if let Some((pixel, _)) = sighting(
            camera,
            max_radius,
            &shot.pose,
            &centre,
            &candidate,
            &structure.blocks,
        ) {
            keypoints.push(Keypoint {
                pixel: [
                    pixel[0] + normal(rng, noise_px),
                    pixel[1] + normal(rng, noise_px),
                ],
                point3d: None,
            });
        }
    }
    keypoints
}

/// Untriangulated keypoints on transient clutter (people, vegetation, reflections):
/// Gaussian clusters in the image.
fn clutter(rng: &mut Pcg64Mcg, camera: &Camera, count: usize) -> Vec<Keypoint> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let cluster_count = (count / 25).max(1);
    let clusters: Vec<[f64; 3]> = (0..cluster_count)
        .map(|_| {
            [
                uniform(rng, 0.0, w),
                uniform(rng, 0.0, h),
                uniform(rng, 0.01, 0.08) * w,
            ]
        })
        .collect();
    let mut keypoints = Vec::with_capacity(count);
    while keypoints.len() < count {
        let [cx, cy, sigma] = clusters[rng.random_range(0..clusters.len())];
        let pixel = [cx + normal(rng, sigma), cy + normal(rng, sigma)];
        if pixel[0] >= 0.0 && pixel[1] >= 0.0 && pixel[0] < w && pixel[1] < h {
            keypoints.push(Keypoint {
                pixel,
                point3d: None,
            });
        }
    }
    keypoints
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_points_the_optical_axis_at_the_target() {
        let centre = Vector3::new(3.0, -4.0, 1.5);
        let target = Vector3::new(0.0, 0.0, 2.0);
        let pose = look_at(&centre, &target, 0.0);
        assert!((pose.center() - centre).norm() < 1e-12);
        let bearing = pose.bearing(&target, 0).unwrap();
        assert!(bearing[0].abs() < 1e-12 && bearing[1].abs() < 1e-12);
        // World up (+z) appears upwards in the image (negative y).
        let above = pose.bearing(&(target + Vector3::z()), 0).unwrap();
        assert!(above[1] < 0.0 && above[0].abs() < 1e-12);
    }

    #[test]
    fn box_faces_point_outwards_and_boxes_occlude() {
        let block = Block {
            centre: Vector3::new(0.0, 0.0, 1.0),
            half: Vector3::new(2.0, 1.0, 1.0),
            yaw: 0.4,
        };
        for face in block.faces() {
            let (p, n) = face.at(0.5, 0.5);
            assert!(n.dot(&(p - block.centre)) > 0.0);
        }
        let front = Vector3::new(0.0, -10.0, 1.0);
        let behind = Vector3::new(0.0, 10.0, 1.0);
        assert!(block.hides(&front, &behind));
        assert!(!block.hides(&front, &Vector3::new(10.0, -10.0, 1.0)));
        // A point on the face towards the viewer does not hide itself.
        let (on_face, _) = block.faces()[3].at(0.5, 0.5);
        assert!(!block.hides(&front, &on_face));
        assert!(block.contains(&block.centre) && !block.contains(&front));
    }

    #[test]
    fn intrinsics_of_every_model_round_trip_inside_the_image() {
        let mut rng = Pcg64Mcg::seed_from_u64(3);
        for model in MODELS.iter().map(|spec| spec.model) {
            let camera = random_intrinsics(&mut rng, model, 1600, 1200, 70f64.to_radians());
            assert_eq!(camera.model, model);
            for pixel in [[0.0, 0.0], [1600.0, 1200.0], [800.0, 100.0]] {
                let bearing = camera.pixel_to_bearing(pixel).unwrap();
                let back = camera.bearing_to_pixel(bearing).unwrap();
                assert!((back[0] - pixel[0]).abs() < 1e-6 && (back[1] - pixel[1]).abs() < 1e-6);
            }
            assert!(max_bearing_radius(&camera) > 0.5);
        }
    }

    #[test]
    fn scenes_are_deterministic_valid_and_sfm_like() {
        for index in 0..4 {
            let scene = synthetic_scene(11, index);
            assert_eq!(scene, synthetic_scene(11, index));
            scene.validate().unwrap();
            assert_eq!(scene.name, format!("synthetic/{index:04}"));
            let images = scene.images.len();
            assert!((35..=90).contains(&images));
            let keypoints: usize = scene.images.values().map(|i| i.keypoints.len()).sum();
            let triangulated: usize = scene.images.values().map(Image::triangulated_count).sum();
            let mean = keypoints as f64 / images as f64;
            let outlier_rate = 1.0 - triangulated as f64 / keypoints as f64;
            assert!(
                (100.0..=2000.0).contains(&mean),
                "{mean} keypoints per image"
            );
            assert!(
                (0.25..=0.75).contains(&outlier_rate),
                "outlier rate {outlier_rate}"
            );
            assert!(scene.points.values().all(|p| p.track.len() >= 2));
            let error = scene.median_reprojection_error(None, 0).unwrap();
            assert!(
                (0.3..=1.2).contains(&error),
                "median reprojection {error} px"
            );
        }
        assert_ne!(synthetic_scene(11, 0), synthetic_scene(12, 0));
    }

    #[test]
    fn collections_mix_zooms_distortions_and_keypoint_counts() {
        let scene = collection_scene(4, 0);
        assert_eq!(scene, collection_scene(4, 0));
        scene.validate().unwrap();
        assert_eq!(scene.name, "collection/0000");
        assert_eq!(
            scene.cameras.len(),
            scene.images.len(),
            "one camera per photo"
        );
        let fovs: Vec<f64> = scene
            .cameras
            .values()
            .map(|c| 2.0 * (0.5 * f64::from(c.width) / c.focal[0]).atan().to_degrees())
            .collect();
        let (min, max) = COLLECTION_FOV_DEG;
        assert!(fovs.iter().all(|f| (min - 1e-9..=max + 1e-9).contains(f)));
        assert!(fovs.iter().any(|&f| f < 30.0) && fovs.iter().any(|&f| f > 60.0));
        let keypoints: Vec<usize> = scene.images.values().map(|i| i.keypoints.len()).collect();
        assert!(keypoints.iter().any(|&k| k < 600) && keypoints.iter().any(|&k| k > 2000));
        let error = scene.median_reprojection_error(None, 0).unwrap();
        assert!(
            (0.3..=1.2).contains(&error),
            "median reprojection {error} px"
        );
    }
}
