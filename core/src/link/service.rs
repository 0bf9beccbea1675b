//! The device's side of a request: the model and map it serves, and one answer per request.

use core::convert::Infallible;

use embedded_hal::digital::{ErrorType, OutputPin};

use super::messages::{
    decode_keypoints, rejected, DeviceInfo, LinkError, LocalizeReply, LocalizeRequest, MapInfo,
    ModelInfo, Rejection, ResponseBody, Views,
};
use super::wire::{narrow, KEYPOINT_BYTES, PROTOCOL_VERSION};
use crate::localizer::{Clock, Localizer, LocalizerConfig, Query, ViewSelection, MAX_VIEWS};
use crate::map::{Map, MAP_VERSION};
use crate::sinkhorn::PlanScalar;
use crate::weights::{Model, MODEL_VERSION};

/// A busy pin for devices without one.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoPin;

impl ErrorType for NoPin {
    type Error = Infallible;
}

impl OutputPin for NoPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// What the device serves: the localizer workspace, the model and map read in place, the
/// settings, a busy pin (high while a localization runs) and an optional clock.
pub struct Service<'a, const N: usize, S: PlanScalar, P: OutputPin> {
    localizer: &'a mut Localizer<N, S>,
    model: Model<'a>,
    map: Map<'a>,
    model_bytes: usize,
    map_bytes: usize,
    /// Settings of every localization.
    pub config: LocalizerConfig,
    busy: P,
    clock: Option<&'a dyn Clock>,
}

impl<'a, const N: usize, S: PlanScalar, P: OutputPin> Service<'a, N, S, P> {
    /// Validates the model and map blobs once ([`Model::from_bytes`],
    /// [`Map::from_bytes`]) and sets the busy pin low.
    pub fn new(
        localizer: &'a mut Localizer<N, S>,
        model_blob: &'a [u8],
        map_blob: &'a [u8],
        mut busy: P,
    ) -> crate::error::Result<Self> {
        let model = Model::from_bytes(model_blob)?;
        let map = Map::from_bytes(map_blob)?;
        // A pin that cannot be driven is no reason not to serve.
        let _ = busy.set_low();
        Ok(Service {
            localizer,
            model,
            map,
            model_bytes: model_blob.len(),
            map_bytes: map_blob.len(),
            config: LocalizerConfig::new(),
            busy,
            clock: None,
        })
    }

    /// The service with the map's precomputed view features ([`crate::view_features`]),
    /// checked against the map ([`Map::with_view_features`]).
    pub fn with_view_features(mut self, blob: &'a [u8]) -> crate::error::Result<Self> {
        let features = crate::view_features::ViewFeatures::from_bytes(blob)?;
        self.map = self.map.with_view_features(features)?;
        Ok(self)
    }

    /// Stage timings from this clock go into every [`LocalizeReply`].
    pub fn with_clock(mut self, clock: &'a dyn Clock) -> Self {
        self.clock = Some(clock);
        self
    }

    /// The answer to [`RequestBody::Info`](super::RequestBody::Info) for a receive buffer of `rx_frame_bytes`.
    pub fn info(&self, rx_frame_bytes: usize) -> DeviceInfo {
        DeviceInfo {
            protocol_version: PROTOCOL_VERSION,
            capacity: narrow(N),
            max_views: MAX_VIEWS as u8,
            sinkhorn_bytes: core::mem::size_of::<S>() as u8,
            workspace_bytes: narrow(Localizer::<N, S>::BYTES),
            rx_frame_bytes: narrow(rx_frame_bytes),
            model: ModelInfo {
                format_version: MODEL_VERSION,
                precision: self.model.precision(),
                config: *self.model.config(),
                bytes: narrow(self.model_bytes),
            },
            map: MapInfo {
                format_version: MAP_VERSION,
                points: narrow(self.map.point_count()),
                views: narrow(self.map.view_count()),
                cameras: narrow(self.map.camera_count()),
                observations: narrow(self.map.observation_count()),
                bytes: narrow(self.map_bytes),
            },
        }
    }

    /// Runs one localization request with its keypoints decoded into `keypoints`.
    pub fn localize(
        &mut self,
        request: &LocalizeRequest<'_>,
        keypoints: &mut [[f32; 2]; N],
    ) -> ResponseBody {
        let n = match decode_request_keypoints(request.keypoints, keypoints) {
            Ok(n) => n,
            Err(error) => return ResponseBody::Error(error),
        };
        let views = match view_selection(&request.views) {
            Ok(views) => views,
            Err(rejection) => return rejected(rejection),
        };
        let query = Query {
            keypoints: keypoints.get(..n).unwrap_or(&[]),
            camera: request.camera,
        };
        let _ = self.busy.set_high();
        let result = self.localizer.localize(
            &self.model,
            &self.map,
            &query,
            views,
            &self.config,
            self.clock,
        );
        let _ = self.busy.set_low();
        match result {
            Ok(localization) => ResponseBody::Localized(LocalizeReply::from(&localization)),
            Err(e) => rejected(Rejection::from(&e)),
        }
    }
}

/// Decodes a request's keypoint bytes into `out`: how many, or the refusal of bytes that
/// are not whole keypoints or of more keypoints than `out` holds.
fn decode_request_keypoints(bytes: &[u8], out: &mut [[f32; 2]]) -> Result<usize, LinkError> {
    if !bytes.len().is_multiple_of(KEYPOINT_BYTES) {
        return Err(LinkError::KeypointBytes {
            len: narrow(bytes.len()),
        });
    }
    decode_keypoints(bytes, out).ok_or(LinkError::Rejected(Rejection::TooManyKeypoints {
        capacity: narrow(out.len()),
        requested: narrow(bytes.len() / KEYPOINT_BYTES),
    }))
}

/// The localizer's view selection of a request, or the refusal of more than [`MAX_VIEWS`]
/// views or of a non-finite prior.
fn view_selection(views: &Views) -> Result<ViewSelection<'_>, Rejection> {
    match views {
        Views::ImageIds(ids) => Ok(ViewSelection::ImageIds(ids.as_slice())),
        Views::NearPrior {
            prior,
            k,
            max_angle_deg,
        } => {
            if usize::from(*k) > MAX_VIEWS {
                return Err(Rejection::TooManyViews {
                    capacity: MAX_VIEWS as u32,
                    requested: u32::from(*k),
                });
            }
            let prior = prior.to_pose().map_err(|e| Rejection::from(&e))?;
            Ok(ViewSelection::NearPrior {
                prior,
                k: usize::from(*k),
                max_angle_deg: *max_angle_deg,
            })
        }
    }
}

/// What one [`Device::serve`](super::Device::serve) call did.
#[derive(Debug, Clone, PartialEq)]
pub enum Served {
    /// A request with this id was answered.
    Answered {
        /// The request's id.
        id: u32,
    },
    /// A frame was refused with this error (and the error was sent).
    Refused(LinkError),
    /// The stream ended (a partial frame is dropped).
    Closed,
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::vec::Vec;

    use crate::link::messages::rejected;
    use crate::link::tests_support::{fixture, frame, localize_request, pose, serve, CAP};
    use crate::link::*;

    #[test]
    fn refused_inputs_name_the_reason() {
        let (model, map, pixels) = fixture();
        let mut too_many = pixels.clone();
        too_many.push([1.0, 1.0]);
        let mut nan = pixels.clone();
        nan[7][0] = f32::NAN;
        let wire = |p: &[[f32; 2]]| {
            let mut bytes = std::vec![0u8; KEYPOINT_BYTES * p.len()];
            encode_keypoints(p, &mut bytes).expect("fits");
            bytes
        };
        let mut near = localize_request(3, &wire(&pixels), &[]);
        if let RequestBody::Localize(r) = &mut near.body {
            r.views = Views::NearPrior {
                prior: WirePose::from(&pose(0.0)),
                k: 11,
                max_angle_deg: 30.0,
            };
        }
        let mut input = frame(&localize_request(1, &wire(&too_many), &[10]));
        input.extend(frame(&localize_request(2, &wire(&nan), &[10])));
        input.extend(frame(&near));
        let (_, replies) = serve(input, &model, &map);
        let bodies: Vec<ResponseBody> = replies.into_iter().map(|r| r.body).collect();
        assert_eq!(
            bodies,
            [
                rejected(Rejection::TooManyKeypoints {
                    capacity: CAP as u32,
                    requested: CAP as u32 + 1
                }),
                rejected(Rejection::NonFiniteKeypoint { index: 7 }),
                rejected(Rejection::TooManyViews {
                    capacity: 10,
                    requested: 11
                }),
            ]
        );
    }
}
