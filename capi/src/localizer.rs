//! The localizer workspace in caller memory, and the calls that use it.

use core::ffi::c_void;
use core::mem::{align_of, size_of};
use core::ptr::{addr_of_mut, NonNull};

use gomatch::error::{Error, Input};
use gomatch::link::Rejection;
use gomatch::localizer::{Correspondence, Localization, LocalizerConfig, Query, ViewSelection};
use gomatch::{Localizer, Map, Model};
use half::f16;

use crate::blobs::{gomatch_map, gomatch_model, opened_map, opened_model};
use crate::error::checked;
use crate::error::{gomatch_error, query_error};
use crate::types::{
    gomatch_inlier, gomatch_query, gomatch_result, gomatch_view_selection, gomatch_views, narrow,
    GOMATCH_MAX_VIEWS,
};

use gomatch_error::*;

/// Alignment of a workspace's memory, in bytes.
pub const GOMATCH_LOCALIZER_ALIGN: usize = 8;
/// Bytes of a workspace of capacity 128 (`gomatch_localizer_bytes(128)`).
pub const GOMATCH_LOCALIZER_BYTES_128: usize = 523_368;
/// Bytes of a workspace of capacity 256 (`gomatch_localizer_bytes(256)`).
pub const GOMATCH_LOCALIZER_BYTES_256: usize = 1_046_248;
/// Bytes of a workspace of capacity 1024 (`gomatch_localizer_bytes(1024)`).
pub const GOMATCH_LOCALIZER_BYTES_1024: usize = 5_559_784;

/// A workspace: memory placed by the caller and set up by `gomatch_localizer_init`. It
/// serves one call at a time: one workspace per concurrent caller.
pub struct gomatch_localizer {
    _private: [u8; 0],
}

/// The layout of a workspace of capacity `N`: the API's header, then the core's
/// localizer with its Sinkhorn cost stored as f16.
#[repr(C)]
struct Workspace<const N: usize> {
    header: Header,
    localizer: Localizer<N, f16>,
}

/// What the API keeps beside the localizer.
#[repr(C)]
struct Header {
    /// [`MAGIC`] once initialised.
    magic: u32,
    /// The capacity `N`.
    capacity: u32,
    /// The calls for this capacity.
    ops: &'static Ops,
    /// The outcome of the last `gomatch_localize` call.
    last: Last,
    /// Whether the last call reached the core's localizer, whose correspondences are then
    /// that call's (else there are none).
    matched: bool,
}

/// `Header::magic` of an initialised workspace.
const MAGIC: u32 = 0x474d_4c5a; // "GMLZ"

/// The outcome of the last `gomatch_localize` call that read its query.
// One per workspace, beside a localizer of a megabyte: no heap to box the large variant into.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub(crate) enum Last {
    /// None since the workspace was initialised, or the call was refused before.
    Nothing,
    /// The localization (a pose or a failure).
    Localized(Localization),
    /// The query was refused for its content, as the device link says it.
    Refused(Rejection),
}

/// The calls of a capacity, reached through the workspace so that an image links the
/// capacities it initialises only.
struct Ops {
    /// `Localizer::localize` with the Sinkhorn cost in f16 and no clock.
    localize: LocalizeFn,
    /// `Localizer::correspondences`.
    correspondences: unsafe fn(NonNull<Header>) -> *const [Correspondence],
}

/// The signature of [`Ops::localize`].
type LocalizeFn = unsafe fn(
    NonNull<Header>,
    &Model<'_>,
    &Map<'_>,
    &Query<'_>,
    ViewSelection<'_>,
) -> Result<Localization, Error>;

/// Settings of every localization: the core's defaults.
static CONFIG: LocalizerConfig = LocalizerConfig::new();

impl<const N: usize> Workspace<N> {
    const OPS: Ops = Ops {
        localize: Self::localize,
        correspondences: Self::correspondences,
    };

    /// # Safety
    /// `header` heads an initialised `Workspace<N>` that nothing else uses during the call.
    unsafe fn localize(
        header: NonNull<Header>,
        model: &Model<'_>,
        map: &Map<'_>,
        query: &Query<'_>,
        views: ViewSelection<'_>,
    ) -> Result<Localization, Error> {
        // SAFETY: the caller's promise; the pointer's provenance is the whole workspace.
        let workspace = unsafe { header.cast::<Self>().as_mut() };
        workspace
            .localizer
            .localize(model, map, query, views, &CONFIG, None)
    }

    /// # Safety
    /// `header` heads an initialised `Workspace<N>`, not written while the slice is used.
    unsafe fn correspondences(header: NonNull<Header>) -> *const [Correspondence] {
        // SAFETY: the caller's promise.
        let workspace = unsafe { header.cast::<Self>().as_ref() };
        workspace.localizer.correspondences()
    }

    /// Sets up a workspace of this capacity in `memory` (of `bytes` bytes).
    ///
    /// # Safety
    /// `memory` must be valid for writes of `bytes` bytes, unused by anything else.
    unsafe fn init(memory: NonNull<u8>, bytes: usize) -> Result<NonNull<Header>, gomatch_error> {
        if bytes < workspace_bytes(N) {
            return Err(GOMATCH_ERROR_WORKSPACE_TOO_SMALL);
        }
        let workspace = memory.cast::<Self>().as_ptr();
        // SAFETY: `memory` is aligned (checked by the caller) and holds a `Workspace<N>`
        // (`workspace_bytes(N) >= size_of`, checked at compile time). `Localizer::new()`
        // is all zero (its `static`s land in `.bss`) and every field of it is a number, a
        // `bool` or an array of them, for which zero bytes are the values `new` gives: so
        // zeroing writes the empty localizer in place, without a 1 MiB temporary on the
        // stack.
        unsafe {
            addr_of_mut!((*workspace).localizer).write_bytes(0, 1);
            addr_of_mut!((*workspace).header).write(Header {
                magic: MAGIC,
                capacity: N as u32,
                ops: &Self::OPS,
                last: Last::Nothing,
                matched: false,
            });
        }
        Ok(memory.cast())
    }
}

/// The size of a workspace of capacity `capacity` (0: not built), the same on every target.
const fn workspace_bytes(capacity: usize) -> usize {
    match capacity {
        128 => GOMATCH_LOCALIZER_BYTES_128,
        256 => GOMATCH_LOCALIZER_BYTES_256,
        1024 => GOMATCH_LOCALIZER_BYTES_1024,
        _ => 0,
    }
}

/// The advertised sizes and alignment hold the workspaces on every target, exactly on
/// 64-bit ones.
const _: () = {
    const fn fits<const N: usize>() -> bool {
        let (size, align) = (size_of::<Workspace<N>>(), align_of::<Workspace<N>>());
        let exact = size == workspace_bytes(N) && align == GOMATCH_LOCALIZER_ALIGN;
        size <= workspace_bytes(N)
            && align <= GOMATCH_LOCALIZER_ALIGN
            && (exact || cfg!(not(target_pointer_width = "64")))
    }
    assert!(fits::<128>() && fits::<256>() && fits::<1024>());
};

/// Bytes of the workspace for `capacity` keypoints per query (and points per view): 128,
/// 256 or 1024; 0 for a capacity this library was not built for. The same as
/// `GOMATCH_LOCALIZER_BYTES_<capacity>`, on every target.
#[no_mangle]
pub extern "C" fn gomatch_localizer_bytes(capacity: u32) -> usize {
    workspace_bytes(capacity as usize)
}

/// Sets up a workspace of capacity `N` in `memory` and writes its handle to `localizer`.
///
/// # Safety
/// `memory` must be NULL or valid for writes of `bytes` bytes and used by nothing else;
/// `localizer` NULL or writable.
unsafe fn init_workspace<const N: usize>(
    memory: *mut c_void,
    bytes: usize,
    localizer: *mut *mut gomatch_localizer,
) -> gomatch_error {
    let out = match checked(localizer) {
        Ok(out) => out,
        Err(e) => return e,
    };
    let Some(memory) = NonNull::new(memory.cast::<u8>()) else {
        return GOMATCH_ERROR_NULL_POINTER;
    };
    if !(memory.as_ptr() as usize).is_multiple_of(GOMATCH_LOCALIZER_ALIGN) {
        return GOMATCH_ERROR_MISALIGNED;
    }
    // SAFETY: `memory` is non-null, aligned and, as the caller promises, valid for `bytes`
    // bytes; `init` checks `bytes`.
    match unsafe { Workspace::<N>::init(memory, bytes) } {
        Ok(header) => {
            // SAFETY: checked above.
            unsafe { out.as_ptr().write(header.as_ptr().cast()) };
            GOMATCH_OK
        }
        Err(e) => e,
    }
}

/// `gomatch_localizer_init(memory, bytes, 128, localizer)`.
///
/// # Safety
/// `memory` must be NULL or valid for writes of `bytes` bytes and used by nothing else;
/// `localizer` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_localizer_init_128(
    memory: *mut c_void,
    bytes: usize,
    localizer: *mut *mut gomatch_localizer,
) -> gomatch_error {
    // SAFETY: the caller's promise.
    unsafe { init_workspace::<128>(memory, bytes, localizer) }
}

/// `gomatch_localizer_init(memory, bytes, 256, localizer)`.
///
/// # Safety
/// `memory` must be NULL or valid for writes of `bytes` bytes and used by nothing else;
/// `localizer` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_localizer_init_256(
    memory: *mut c_void,
    bytes: usize,
    localizer: *mut *mut gomatch_localizer,
) -> gomatch_error {
    // SAFETY: the caller's promise.
    unsafe { init_workspace::<256>(memory, bytes, localizer) }
}

/// `gomatch_localizer_init(memory, bytes, 1024, localizer)`.
///
/// # Safety
/// `memory` must be NULL or valid for writes of `bytes` bytes and used by nothing else;
/// `localizer` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_localizer_init_1024(
    memory: *mut c_void,
    bytes: usize,
    localizer: *mut *mut gomatch_localizer,
) -> gomatch_error {
    // SAFETY: the caller's promise.
    unsafe { init_workspace::<1024>(memory, bytes, localizer) }
}

/// The header of an initialised workspace.
fn workspace(localizer: *const gomatch_localizer) -> Result<NonNull<Header>, gomatch_error> {
    let header = checked(localizer.cast::<Header>())?;
    // SAFETY: non-null and aligned; the caller's handle is a workspace's memory, whose
    // first word is readable (at worst not yet initialised: then not the mark).
    let magic = unsafe { header.cast::<u32>().read() };
    if magic != MAGIC {
        return Err(GOMATCH_ERROR_NOT_INITIALIZED);
    }
    Ok(header)
}

/// Localizes one query: matches its keypoints against the selected views of the map with
/// the model, then estimates the pose. Writes `*result` (on an error: no pose, no counts).
/// A valid query that cannot be localized is `GOMATCH_OK` with `result->localized` false
/// and the reason in `result->failure`. Deterministic: the result depends on the inputs
/// only, not on earlier calls.
///
/// # Safety
/// Each pointer must be NULL or point to its type: `localizer` a workspace used by no
/// other call meanwhile, `model` and `map` handles whose blobs are still valid, `query`'s
/// `keypoints` (when not NULL) `keypoint_count` keypoints.
#[no_mangle]
pub unsafe extern "C" fn gomatch_localize(
    localizer: *mut gomatch_localizer,
    model: *const gomatch_model,
    map: *const gomatch_map,
    query: *const gomatch_query,
    result: *mut gomatch_result,
) -> gomatch_error {
    let result = match checked(result) {
        Ok(result) => result.as_ptr(),
        Err(e) => return e,
    };
    // SAFETY: checked.
    unsafe { result.write(gomatch_result::EMPTY) };
    let mut header = match workspace(localizer) {
        Ok(header) => header,
        Err(e) => return e,
    };
    // SAFETY: an initialised workspace, used by this call only (the caller's promise).
    let head = unsafe { header.as_mut() };
    head.last = Last::Nothing;
    head.matched = false;
    // SAFETY: the caller's promise on the handles and the query.
    let checked_inputs = unsafe {
        (
            opened_model(model),
            opened_map(map),
            checked(query).map(|q| q.read()),
        )
    };
    let (model, map, query) = match checked_inputs {
        (Ok(model), Ok(map), Ok(query)) => (model, map, query),
        (Err(e), _, _) | (_, Err(e), _) | (_, _, Err(e)) => return e,
    };
    let capacity = head.capacity as usize;
    let ops = head.ops;
    // SAFETY: the caller's promise on the query's keypoints.
    let outcome = match unsafe { read_query(&query, capacity) } {
        Ok((keypoints, camera, views)) => {
            let query = Query { keypoints, camera };
            // SAFETY: as above (the call below takes the workspace next).
            unsafe { header.as_mut().matched = true };
            // SAFETY: `ops` belongs to the workspace's capacity; no reference into the
            // workspace is alive across the call.
            match unsafe { (ops.localize)(header, model, map, &query, views) } {
                Ok(localization) => Ok(localization),
                Err(e) => Err((query_error(&e), Some(Rejection::from(&e)))),
            }
        }
        Err(refused) => Err(refused),
    };
    // SAFETY: as above; the localizer's borrow has ended.
    let head = unsafe { header.as_mut() };
    match outcome {
        Ok(localization) => {
            head.last = Last::Localized(localization);
            let min_confidence = CONFIG.acceptance_rule(capacity).min_confidence;
            // SAFETY: checked.
            unsafe {
                result.write(gomatch_result::from_localization(
                    &localization,
                    min_confidence,
                ))
            };
            GOMATCH_OK
        }
        Err((code, rejection)) => {
            if let Some(rejection) = rejection {
                head.last = Last::Refused(rejection);
            }
            code
        }
    }
}

/// A refusal: its code, and what the device link replies when the query's content is
/// the reason.
type Refusal = (gomatch_error, Option<Rejection>);

/// The core's keypoints, camera and views of a query, checked.
///
/// # Safety
/// `query.keypoints`, when not NULL, must point to `query.keypoint_count` keypoints.
unsafe fn read_query(
    query: &gomatch_query,
    capacity: usize,
) -> Result<(&[[f32; 2]], gomatch::Camera, ViewSelection<'_>), Refusal> {
    let n = query.keypoint_count;
    if n > capacity {
        let rejection = Rejection::TooManyKeypoints {
            capacity: narrow(capacity),
            requested: narrow(n),
        };
        return Err((GOMATCH_ERROR_TOO_MANY_KEYPOINTS, Some(rejection)));
    }
    let keypoints: &[[f32; 2]] = if n == 0 {
        &[]
    } else {
        let first = checked(query.keypoints).map_err(|e| (e, None))?;
        // SAFETY: non-null, aligned, `n` keypoints as the caller promises (at most the
        // capacity, so far below `isize::MAX` bytes).
        unsafe { core::slice::from_raw_parts(first.as_ptr(), n) }
    };
    let views = read_views(&query.views)?;
    let camera = query
        .camera
        .to_camera()
        .map_err(|e| (e, Some(Rejection::InvalidCamera)))?;
    Ok((keypoints, camera, views))
}

/// The core's view selection, checked.
fn read_views(views: &gomatch_views) -> Result<ViewSelection<'_>, Refusal> {
    let too_many = |requested: u32| {
        let rejection = Rejection::TooManyViews {
            capacity: GOMATCH_MAX_VIEWS as u32,
            requested,
        };
        (GOMATCH_ERROR_TOO_MANY_VIEWS, Some(rejection))
    };
    const IMAGE_IDS: u32 = gomatch_view_selection::GOMATCH_VIEWS_IMAGE_IDS as u32;
    const NEAR_PRIOR: u32 = gomatch_view_selection::GOMATCH_VIEWS_NEAR_PRIOR as u32;
    match views.selection {
        IMAGE_IDS => {
            let count = views.image_id_count;
            let ids = views.image_ids.get(..count as usize);
            ids.map(ViewSelection::ImageIds).ok_or(too_many(count))
        }
        NEAR_PRIOR => {
            if views.k as usize > GOMATCH_MAX_VIEWS {
                return Err(too_many(views.k));
            }
            let prior = views.prior.to_prior().map_err(|e| {
                let error = Error::NonFinite {
                    input: Input::Pose,
                    index: 0,
                };
                (e, Some(Rejection::from(&error)))
            })?;
            let angle = views.max_angle_deg;
            if !(angle.is_finite() && angle >= 0.0) {
                let error = Error::InvalidConfig {
                    parameter: "max_angle_deg",
                };
                return Err((GOMATCH_ERROR_INVALID_PRIOR, Some(Rejection::from(&error))));
            }
            Ok(ViewSelection::NearPrior {
                prior,
                k: views.k as usize,
                max_angle_deg: angle,
            })
        }
        _ => Err((GOMATCH_ERROR_INVALID_ARGUMENT, None)),
    }
}

/// Copies the inliers of the last localization's pose (none when it was not localized)
/// to `out`, which holds `capacity` of them, and writes their number to `*count`. When
/// they do not fit: `GOMATCH_ERROR_BUFFER_TOO_SMALL`, none copied, `*count` still set (to
/// ask for the number, pass `out` = NULL and `capacity` = 0).
///
/// # Safety
/// `localizer` must be NULL or a workspace not written during the call; `out` NULL or
/// writable for `capacity` inliers; `count` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_inliers(
    localizer: *const gomatch_localizer,
    out: *mut gomatch_inlier,
    capacity: usize,
    count: *mut usize,
) -> gomatch_error {
    let count = match checked(count) {
        Ok(count) => count.as_ptr(),
        Err(e) => return e,
    };
    // SAFETY: the caller's promise on `localizer`.
    let correspondences = match unsafe { last_correspondences(localizer) } {
        Ok(c) => c,
        Err(e) => return e,
    };
    let inliers = correspondences.iter().filter(|c| c.inlier);
    let n = inliers.clone().count();
    // SAFETY: checked.
    unsafe { count.write(n) };
    if n > capacity {
        return GOMATCH_ERROR_BUFFER_TOO_SMALL;
    }
    if n == 0 {
        return GOMATCH_OK;
    }
    let out = match checked(out) {
        Ok(out) => out.as_ptr(),
        Err(e) => return e,
    };
    for (i, c) in inliers.enumerate() {
        let inlier = gomatch_inlier {
            keypoint: u32::from(c.keypoint),
            point: c.point,
            probability: c.probability,
        };
        // SAFETY: `i < n <= capacity`, and `out` is writable for `capacity` inliers.
        unsafe { out.add(i).write(inlier) };
    }
    GOMATCH_OK
}

/// Writes to `*digest` a fingerprint of the last localization's merged correspondences
/// (FNV-1a of each one's keypoint, map point, probability bits, view and inlier flag): a
/// one-ulp difference in any match probability changes it, so two builds that print the
/// same digest matched bit for bit. 0x811c9dc5 when there are none.
///
/// # Safety
/// `localizer` must be NULL or a workspace not written during the call; `digest` NULL or
/// writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_correspondences_digest(
    localizer: *const gomatch_localizer,
    digest: *mut u32,
) -> gomatch_error {
    let digest = match checked(digest) {
        Ok(digest) => digest.as_ptr(),
        Err(e) => return e,
    };
    // SAFETY: the caller's promise on `localizer`.
    match unsafe { last_correspondences(localizer) } {
        Ok(correspondences) => {
            // SAFETY: checked.
            unsafe { digest.write(gomatch::merge::digest(correspondences)) };
            GOMATCH_OK
        }
        Err(e) => e,
    }
}

/// The merged correspondences of the workspace's last localization.
///
/// # Safety
/// `localizer` must be NULL or a workspace not written while the slice is used.
unsafe fn last_correspondences<'w>(
    localizer: *const gomatch_localizer,
) -> Result<&'w [Correspondence], gomatch_error> {
    let header = workspace(localizer)?;
    // SAFETY: an initialised workspace (its mark is set), not written meanwhile.
    unsafe {
        let head = header.as_ref();
        if !head.matched {
            return Ok(&[]);
        }
        Ok(&*(head.ops.correspondences)(header))
    }
}

/// The outcome of the workspace's last localization.
///
/// # Safety
/// `localizer` must be NULL or a workspace not written during the call.
pub(crate) unsafe fn last_outcome(
    localizer: *const gomatch_localizer,
) -> Result<Last, gomatch_error> {
    let header = workspace(localizer)?;
    // SAFETY: an initialised workspace, not written meanwhile.
    Ok(unsafe { header.as_ref().last.clone() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn advertised_sizes_are_the_workspaces() {
        let header = size_of::<Header>();
        assert_eq!(
            gomatch_localizer_bytes(256),
            header + Localizer::<256, f16>::BYTES
        );
        assert_eq!(
            gomatch_localizer_bytes(1024),
            header + Localizer::<1024, f16>::BYTES
        );
        assert_eq!(
            gomatch_localizer_bytes(128),
            header + Localizer::<128, f16>::BYTES
        );
        assert_eq!(gomatch_localizer_bytes(512), 0);
    }
}
