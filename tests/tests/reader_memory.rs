//! The text readers reserve memory by what a file holds, never by the counts it declares
//! (issue 23): a 16 MiB file that declares 16,777,216 records is refused with a typed error
//! before any reservation, and a plausible count reserves at most a few bytes per byte of
//! the file. A counting global allocator measures the peak of live heap bytes during each
//! parse (one test function, so no other test allocates meanwhile).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use gomatch_sim::readers::bal::parse_bal;
use gomatch_sim::readers::bundler::parse_bundler;
use gomatch_sim::readers::parse::FormatError;

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(bytes: usize) {
    let live = LIVE.fetch_add(bytes, Ordering::SeqCst) + bytes;
    PEAK.fetch_max(live, Ordering::SeqCst);
}

// SAFETY: every call is forwarded to the system allocator unchanged; only counters are
// updated besides.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `alloc`, passed on unchanged.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` with this `layout` (the caller's contract).
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract for `realloc`, passed on unchanged.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
            grew(new_size);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f` and returns its result with the peak of heap bytes it held beyond what was
/// live before.
fn peak_bytes<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let before = LIVE.load(Ordering::SeqCst);
    PEAK.store(before, Ordering::SeqCst);
    let result = f();
    (result, PEAK.load(Ordering::SeqCst) - before)
}

/// `header` followed by `0 ` up to 16 MiB: 8 M tokens.
fn padded(header: &str) -> String {
    let mut text = String::from(header);
    while text.len() < 16 << 20 {
        text.push_str("0 ");
    }
    text
}

#[test]
fn declared_counts_never_reserve_more_than_the_file_holds() {
    // 16,777,216 BAL cameras of 9 values each cannot fit in 8 M tokens.
    let text = padded("16777216 0 0\n");
    let (result, peak) = peak_bytes(|| parse_bal(&text, "bal/padded".into()).map(|_| ()));
    assert!(
        matches!(
            result,
            Err(FormatError::OutOfRange {
                what: "declared record count",
                value: 16_777_216,
                ..
            })
        ),
        "{result:?}"
    );
    assert!(peak < 1 << 20, "BAL header refusal held {peak} bytes");

    let text = padded("# Bundle file v0.3\n16777216 0\n");
    let (result, peak) = peak_bytes(|| parse_bundler(&text, "bundler/padded".into()).map(|_| ()));
    assert!(
        matches!(
            result,
            Err(FormatError::OutOfRange {
                what: "declared record count",
                value: 16_777_216,
                ..
            })
        ),
        "{result:?}"
    );
    assert!(peak < 1 << 20, "Bundler header refusal held {peak} bytes");

    // A count the file can hold (800,000 cameras of 9 zeros: 7.2 M of its 8 M tokens) is
    // read; the file then holds 0.8 M tokens too many. The reader held at most 8 bytes per
    // byte of the file (no 24-byte-per-token list).
    let text = padded("800000 0 0\n");
    let (result, peak) = peak_bytes(|| parse_bal(&text, "bal/plausible".into()).map(|_| ()));
    assert!(
        matches!(result, Err(FormatError::Syntax { .. })),
        "{result:?}"
    );
    assert!(
        peak <= 8 * text.len(),
        "{peak} bytes for a {} byte file",
        text.len()
    );
}
