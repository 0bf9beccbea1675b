//! The camera models, one table entry each, the way PoseLib's `camera_models.h` lists
//! them: the model's COLMAP id (also the id the map blob stores) and name, its parameters
//! in COLMAP order and its lens. Every reader, writer and parser looks models up here.

use serde::{Deserialize, Serialize};

use super::lens::{Lens, LENS_COEFFICIENTS, RADIAL_TANGENTIAL};
use crate::error::{Error, Result};

/// Most parameters of any model (COLMAP `OPENCV`).
pub const MAX_PARAMS: usize = 8;

/// Where one COLMAP parameter of a model goes in a [`crate::Camera`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Param {
    /// One focal length for both axes, `f`.
    Focal,
    /// Horizontal focal length `fx`.
    FocalX,
    /// Vertical focal length `fy`.
    FocalY,
    /// Principal point `cx`.
    PrincipalX,
    /// Principal point `cy`.
    PrincipalY,
    /// Lens coefficient `i` of [`crate::Camera::distortion`] (`k1, k2, p1, p2` of
    /// [`RADIAL_TANGENTIAL`]).
    Coefficient(usize),
}

/// One camera model's declaration.
#[derive(Debug, Clone, Copy)]
pub struct ModelSpec {
    /// The model.
    pub model: CameraModel,
    /// COLMAP's id of the model, also stored in the map blob.
    pub id: i32,
    /// COLMAP's name of the model (`cameras.txt`, query lists).
    pub name: &'static str,
    /// The parameters in COLMAP order; their count is the model's parameter count.
    pub params: &'static [Param],
    /// The lens distortion the model's coefficients parameterise.
    pub lens: Lens,
}

/// Declares [`CameraModel`] and [`MODELS`] from one entry per model, so that adding a
/// model is one entry: `Variant: colmap_id, "COLMAP_NAME", [params], lens;`.
macro_rules! camera_models {
    ($($(#[$doc:meta])* $variant:ident: $id:literal, $name:literal, [$($param:expr),+ $(,)?], $lens:expr;)+) => {
        /// The supported camera models; [`MODELS`] holds each one's declaration.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
        pub enum CameraModel {
            $($(#[$doc])* $variant,)+
        }

        /// Every supported model's declaration, in [`CameraModel`] order.
        pub const MODELS: &[ModelSpec] = &[$(ModelSpec {
            model: CameraModel::$variant,
            id: $id,
            name: $name,
            params: &[$($param),+],
            lens: $lens,
        }),+];
    };
}

use Param::{Coefficient, Focal, FocalX, FocalY, PrincipalX, PrincipalY};

camera_models! {
    /// `f, cx, cy`.
    SimplePinhole: 0, "SIMPLE_PINHOLE", [Focal, PrincipalX, PrincipalY], RADIAL_TANGENTIAL;
    /// `fx, fy, cx, cy`.
    Pinhole: 1, "PINHOLE", [FocalX, FocalY, PrincipalX, PrincipalY], RADIAL_TANGENTIAL;
    /// `f, cx, cy, k`.
    SimpleRadial: 2, "SIMPLE_RADIAL",
        [Focal, PrincipalX, PrincipalY, Coefficient(0)], RADIAL_TANGENTIAL;
    /// `f, cx, cy, k1, k2`.
    Radial: 3, "RADIAL",
        [Focal, PrincipalX, PrincipalY, Coefficient(0), Coefficient(1)], RADIAL_TANGENTIAL;
    /// `fx, fy, cx, cy, k1, k2, p1, p2`.
    OpenCv: 4, "OPENCV", [
        FocalX, FocalY, PrincipalX, PrincipalY,
        Coefficient(0), Coefficient(1), Coefficient(2), Coefficient(3),
    ], RADIAL_TANGENTIAL;
}

// Compile-time checks of the table: entry `i` declares variant `i`, ids and names are
// unique, ids fit the map blob's byte, parameter lists fit `MAX_PARAMS` and lens slots fit
// `LENS_COEFFICIENTS`.
const _: () = {
    let mut i = 0;
    while i < MODELS.len() {
        let spec = &MODELS[i];
        assert!(spec.model as usize == i);
        assert!(spec.id >= 0 && spec.id <= u8::MAX as i32);
        assert!(spec.params.len() <= MAX_PARAMS);
        let mut p = 0;
        while p < spec.params.len() {
            if let Param::Coefficient(slot) = spec.params[p] {
                assert!(slot < LENS_COEFFICIENTS);
            }
            p += 1;
        }
        let mut j = 0;
        while j < i {
            assert!(MODELS[j].id != spec.id);
            assert!(!str_eq(MODELS[j].name, spec.name));
            j += 1;
        }
        i += 1;
    }
};

/// `a == b` in a const context.
const fn str_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    let mut i = 0;
    while i < a.len() {
        if a[i] != b[i] {
            return false;
        }
        i += 1;
    }
    true
}

impl CameraModel {
    /// The model's declaration in [`MODELS`].
    pub fn spec(self) -> &'static ModelSpec {
        &MODELS[self as usize]
    }

    /// Model from its COLMAP id (the id the map blob stores).
    pub fn from_colmap_id(id: i32) -> Result<Self> {
        Self::find(|spec| spec.id == id)
    }

    /// Model from its COLMAP name (`SIMPLE_PINHOLE`, `PINHOLE`, ...).
    pub fn from_colmap_name(name: &str) -> Result<Self> {
        Self::find(|spec| spec.name == name)
    }

    fn find(matches: impl Fn(&ModelSpec) -> bool) -> Result<Self> {
        MODELS
            .iter()
            .find(|spec| matches(spec))
            .map(|spec| spec.model)
            .ok_or(Error::InvalidIntrinsics)
    }

    /// COLMAP id of the model.
    pub fn colmap_id(self) -> i32 {
        self.spec().id
    }

    /// COLMAP name of the model.
    pub fn colmap_name(self) -> &'static str {
        self.spec().name
    }

    /// Number of COLMAP parameters of the model.
    pub fn param_count(self) -> usize {
        self.spec().params.len()
    }
}
