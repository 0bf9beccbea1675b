//! Test fixtures of the link: a pipe, a tiny model and map, request frames, a device run.

extern crate std;

use core::convert::Infallible;
use std::sync::Mutex;
use std::vec::Vec;

use embedded_io::{Read, Write};
use nalgebra::{Rotation3, Vector3};

use super::framing::cobs_len;
use super::*;
use crate::camera::{Camera, CameraModel};
use crate::localizer::Localizer;
use crate::map::{encode, encoded_len, MapViewEntry};
use crate::pose::Pose;
use crate::weights::tests_support::{blob, TINY};

pub(super) const CAP: usize = 64;
pub(super) const RX: usize = rx_frame_len(CAP);
pub(super) static LOCALIZER: Mutex<Localizer<CAP>> = Mutex::new(Localizer::new());
pub(super) static DEVICE: Mutex<Device<CAP, RX>> = Mutex::new(Device::new());

/// A byte stream: reads `input`, collects what is written.
pub(super) struct Pipe {
    input: Vec<u8>,
    at: usize,
    output: Vec<u8>,
}

impl embedded_io::ErrorType for Pipe {
    type Error = Infallible;
}

impl Read for Pipe {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        // Odd read sizes exercise frames split over reads.
        let n = buf.len().min(self.input.len() - self.at).min(37);
        buf[..n].copy_from_slice(&self.input[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

impl Write for Pipe {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        self.output.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

pub(super) fn camera() -> Camera {
    Camera::from_colmap(CameraModel::SimplePinhole, 640, 480, &[500.0, 320.0, 240.0])
        .expect("valid")
}

pub(super) fn pose(x: f64) -> Pose {
    Pose::new(
        Rotation3::from_euler_angles(0.0, 0.05 * x, 0.0),
        Vector3::new(x, 0.0, 0.0),
    )
}

/// Model blob, map blob (80 points seen by views 10 and 20) and the query pixels of
/// those points from `pose(0.1)`.
pub(super) fn fixture() -> (Vec<u8>, Vec<u8>, Vec<[f32; 2]>) {
    let mut model = std::vec![0u8; 64 * 1024];
    let len = blob(&TINY, 5, &mut model);
    model.truncate(len);
    let points = crate::test_scene::wavy_surface();
    let all: Vec<u32> = (0..80).collect();
    let views = [(10, -0.3), (20, 0.3)].map(|(image_id, x)| MapViewEntry {
        image_id,
        name: "",
        camera_index: 0,
        pose: pose(x),
        points: &all,
    });
    let mut map = std::vec![0u8; encoded_len(points.len(), 1, &views)];
    let len = encode(&points, &[camera()], &views, &mut map).expect("encodes");
    map.truncate(len);
    let truth = pose(0.1);
    let pixels = points
        .iter()
        .take(CAP)
        .map(|p| {
            let x = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let b = truth.bearing(&x, 0).expect("in front");
            let px = camera().bearing_to_pixel(b).expect("projects");
            [px[0] as f32, px[1] as f32]
        })
        .collect();
    (model, map, pixels)
}

pub(super) fn localize_request(id: u32, keypoints: &[u8], ids: &[u32]) -> Request<'static> {
    let keypoints: &'static [u8] = std::vec::Vec::leak(keypoints.to_vec());
    Request {
        id,
        body: RequestBody::Localize(LocalizeRequest {
            camera: camera(),
            keypoints,
            views: Views::ImageIds(heapless::Vec::from_slice(ids).expect("<= 10")),
        }),
    }
}

/// `[0]` then the request's frame, as a host sends it.
pub(super) fn frame(request: &Request<'_>) -> Vec<u8> {
    let mut out = std::vec![0u8; rx_frame_len(CAP) + 2];
    let len = encode_frame(request, &mut out[1..]).expect("fits").len();
    out.truncate(len + 1);
    out
}

/// The frame of raw message bytes: COBS of the bytes and their CRC-32, then `[0]`.
pub(super) fn checked(message: &[u8]) -> Vec<u8> {
    let mut body = message.to_vec();
    body.extend(crc32fast::hash(message).to_le_bytes());
    cobs_frame(&body)
}

/// COBS of `body`, then `[0]`.
pub(super) fn cobs_frame(body: &[u8]) -> Vec<u8> {
    let mut out = std::vec![0u8; cobs_len(body.len()) + 1];
    let len = cobs::encode(body, &mut out);
    out.truncate(len + 1);
    out
}

/// Runs the device until the input ends; returns the decoded replies.
pub(super) fn serve(input: Vec<u8>, model: &[u8], map: &[u8]) -> (Vec<Served>, Vec<Response>) {
    let mut localizer = LOCALIZER.lock().expect("lock");
    let mut device = DEVICE.lock().expect("lock");
    let mut service = Service::new(&mut localizer, model, map, NoPin).expect("valid blobs");
    let mut pipe = Pipe {
        input,
        at: 0,
        output: Vec::new(),
    };
    let mut served = Vec::new();
    loop {
        let s = device.serve(&mut pipe, &mut service).expect("infallible");
        if s == Served::Closed {
            break;
        }
        served.push(s);
    }
    let replies = pipe
        .output
        .split_mut(|&b| b == 0)
        .filter(|f| !f.is_empty())
        .map(|f| decode_frame::<Response>(f).expect("device replies decode"))
        .collect();
    (served, replies)
}
