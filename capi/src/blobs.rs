//! The model and map handles: a validated blob, read in place, kept in caller memory.

use core::mem::{align_of, size_of};

use gomatch::{Map, Model};

use crate::error::checked;
use crate::error::{blob_error, gomatch_error};

/// Private: 64-bit words of a `gomatch_model`'s storage (its validated tensor table).
pub const GOMATCH_MODEL_WORDS: usize = 917;
/// Private: 64-bit words of a `gomatch_map`'s storage.
pub const GOMATCH_MAP_WORDS: usize = 18;
/// `gomatch_model::_opened` of an opened model.
const MODEL_OPENED: u32 = 0x474d_5742; // "GMWB"
/// `gomatch_map::_opened` of an opened map.
const MAP_OPENED: u32 = 0x474d_4150; // "GMAP"

const _: () = {
    assert!(size_of::<Model<'static>>() <= 8 * GOMATCH_MODEL_WORDS);
    assert!(align_of::<Model<'static>>() <= 8);
    assert!(size_of::<Map<'static>>() <= 8 * GOMATCH_MAP_WORDS);
    assert!(align_of::<Map<'static>>() <= 8);
};

/// A model blob opened by `gomatch_model_open`: its tensors, read in place. The blob must
/// stay valid and unchanged while the model is used (flash). Read-only once opened: one
/// model may serve any number of workspaces, also concurrently. Its fields are private.
#[repr(C)]
pub struct gomatch_model {
    /// Private: marks an opened model.
    pub _opened: u32,
    /// Private: the validated model.
    pub _storage: [u64; GOMATCH_MODEL_WORDS],
}

/// A map blob opened by `gomatch_map_open`: 3D points, cameras and views, read in place.
/// The blob must stay valid and unchanged while the map is used (flash). Read-only once
/// opened: one map may serve any number of workspaces, also concurrently. Its fields are
/// private.
#[repr(C)]
pub struct gomatch_map {
    /// Private: marks an opened map.
    pub _opened: u32,
    /// Private: the validated map.
    pub _storage: [u64; GOMATCH_MAP_WORDS],
}

/// The blob `bytes`, `len` as a slice, checked for NULL and size.
///
/// # Safety
/// A non-null `bytes` must be valid for reads of `len` bytes for `'static`, unchanged.
unsafe fn blob_slice(bytes: *const u8, len: usize) -> Result<&'static [u8], gomatch_error> {
    if bytes.is_null() {
        return Err(gomatch_error::GOMATCH_ERROR_NULL_POINTER);
    }
    if len > isize::MAX as usize {
        return Err(gomatch_error::GOMATCH_ERROR_INVALID_ARGUMENT);
    }
    // SAFETY: non-null, at most isize::MAX bytes, valid for reads as the caller promises.
    Ok(unsafe { core::slice::from_raw_parts(bytes, len) })
}

/// Opens a model blob in place (no copy): checks its header, checksum, configuration
/// against this build's limits, and every tensor's shape. The blob must stay valid and
/// unchanged while the model is used. On error the model is left unopened.
///
/// # Safety
/// `model` must be NULL or point to a writable `gomatch_model`; `blob` NULL or valid for
/// reads of `len` bytes for as long as the model is used.
#[no_mangle]
pub unsafe extern "C" fn gomatch_model_open(
    model: *mut gomatch_model,
    blob: *const u8,
    len: usize,
) -> gomatch_error {
    let model = match checked(model) {
        // SAFETY: checked; the caller owns the handle for the call, and every bit pattern
        // of it is valid (integers).
        Ok(model) => unsafe { &mut *model.as_ptr() },
        Err(e) => return e,
    };
    model._opened = 0;
    // SAFETY: the caller's promise on `blob`.
    let bytes = match unsafe { blob_slice(blob, len) } {
        Ok(bytes) => bytes,
        Err(e) => return e,
    };
    match Model::from_bytes(bytes) {
        Ok(opened) => {
            // SAFETY: the storage holds a `Model` (size and alignment checked above).
            unsafe {
                model
                    ._storage
                    .as_mut_ptr()
                    .cast::<Model<'static>>()
                    .write(opened)
            };
            model._opened = MODEL_OPENED;
            gomatch_error::GOMATCH_OK
        }
        Err(e) => blob_error(&e),
    }
}

/// Opens a map blob in place (no copy): checks its header, checksum and every index,
/// camera and pose. The blob must stay valid and unchanged while the map is used. On
/// error the map is left unopened.
///
/// # Safety
/// `map` must be NULL or point to a writable `gomatch_map`; `blob` NULL or valid for
/// reads of `len` bytes for as long as the map is used.
#[no_mangle]
pub unsafe extern "C" fn gomatch_map_open(
    map: *mut gomatch_map,
    blob: *const u8,
    len: usize,
) -> gomatch_error {
    let map = match checked(map) {
        // SAFETY: as for the model.
        Ok(map) => unsafe { &mut *map.as_ptr() },
        Err(e) => return e,
    };
    map._opened = 0;
    // SAFETY: the caller's promise on `blob`.
    let bytes = match unsafe { blob_slice(blob, len) } {
        Ok(bytes) => bytes,
        Err(e) => return e,
    };
    match Map::from_bytes(bytes) {
        Ok(opened) => {
            // SAFETY: the storage holds a `Map` (size and alignment checked above).
            unsafe {
                map._storage
                    .as_mut_ptr()
                    .cast::<Map<'static>>()
                    .write(opened)
            };
            map._opened = MAP_OPENED;
            gomatch_error::GOMATCH_OK
        }
        Err(e) => blob_error(&e),
    }
}

/// The model of an opened handle.
///
/// # Safety
/// `model` must be NULL or point to a `gomatch_model` that is not written during the call,
/// and whose blob is still valid if it was opened.
pub(crate) unsafe fn opened_model<'m>(
    model: *const gomatch_model,
) -> Result<&'m Model<'static>, gomatch_error> {
    // SAFETY: checked, and not written during the call.
    let model = unsafe { checked(model)?.as_ref() };
    if model._opened != MODEL_OPENED {
        return Err(gomatch_error::GOMATCH_ERROR_NOT_INITIALIZED);
    }
    // SAFETY: `gomatch_model_open` wrote a `Model` there before it set the mark.
    Ok(unsafe { &*model._storage.as_ptr().cast::<Model<'static>>() })
}

/// The map of an opened handle.
///
/// # Safety
/// As for [`opened_model`].
pub(crate) unsafe fn opened_map<'m>(
    map: *const gomatch_map,
) -> Result<&'m Map<'static>, gomatch_error> {
    // SAFETY: checked, and not written during the call.
    let map = unsafe { checked(map)?.as_ref() };
    if map._opened != MAP_OPENED {
        return Err(gomatch_error::GOMATCH_ERROR_NOT_INITIALIZED);
    }
    // SAFETY: `gomatch_map_open` wrote a `Map` there before it set the mark.
    Ok(unsafe { &*map._storage.as_ptr().cast::<Map<'static>>() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn storage_fits_the_handles_closely() {
        assert!(8 * GOMATCH_MODEL_WORDS - size_of::<Model<'static>>() < 64);
        assert!(8 * GOMATCH_MAP_WORDS - size_of::<Map<'static>>() < 64);
    }
}
