//! Multi-view merge (paper Sec. 4, "merge results from k pairs based on their matching
//! scores"): each query keypoint keeps its most probable accepted match over the co-visible
//! views, then each 3D point keeps its most probable keypoint.

/// One merged 2D-3D correspondence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    /// Index of the query keypoint.
    pub keypoint: u16,
    /// Index of the 3D point in the map.
    pub point: u32,
    /// Best classifier probability of the pair across views.
    pub probability: f32,
    /// Position, in the selection, of the view that gave that probability.
    pub view: u8,
    /// Inlier of the final (accepted) pose.
    pub inlier: bool,
}

impl Correspondence {
    /// An empty slot.
    pub const EMPTY: Self = Correspondence {
        keypoint: 0,
        point: 0,
        probability: 0.0,
        view: 0,
        inlier: false,
    };
}

/// FNV-1a (32 bits) of the correspondences' fields (keypoint, point, probability bits,
/// view, inlier flag, little-endian): a fingerprint of the network's output that shows a
/// one-ulp difference in any probability, for comparing runs across machines.
pub fn digest(correspondences: &[Correspondence]) -> u32 {
    let mut hash = 0x811c_9dc5u32;
    for c in correspondences {
        let fields = [
            &c.keypoint.to_le_bytes()[..],
            &c.point.to_le_bytes(),
            &c.probability.to_bits().to_le_bytes(),
            &[c.view, u8::from(c.inlier)],
        ];
        for &byte in fields.iter().flat_map(|f| f.iter()) {
            hash = (hash ^ u32::from(byte)).wrapping_mul(0x0100_0193);
        }
    }
    hash
}

/// Probability of a keypoint without an accepted match while the views are matched. A
/// match is accepted when its probability is above the model's (finite) threshold, so it
/// is never `-inf`.
const UNMATCHED: f32 = f32::NEG_INFINITY;

/// Marks every slot as keypoint `i` (its index) without an accepted match yet.
pub fn clear(slots: &mut [Correspondence]) {
    for (keypoint, slot) in slots.iter_mut().enumerate() {
        *slot = Correspondence {
            keypoint: keypoint as u16,
            probability: UNMATCHED,
            ..Correspondence::EMPTY
        };
    }
}

/// Keeps an accepted match of one view in its keypoint's slot when it is more probable
/// than the slot's best so far.
pub fn keep_best(slot: &mut Correspondence, point: u32, probability: f32, view: u8) {
    if probability > slot.probability {
        (slot.point, slot.probability, slot.view) = (point, probability, view);
    }
}

/// Turns the per-keypoint slots into correspondences where each 3D point also appears once
/// (its most probable keypoint; ties to the lower keypoint index), sorted by keypoint, at
/// the front of `slots`; returns their number.
pub fn merge(slots: &mut [Correspondence]) -> usize {
    let mut len = 0;
    for i in 0..slots.len() {
        if slots[i].probability != UNMATCHED {
            slots[len] = slots[i];
            len += 1;
        }
    }
    let merged = &mut slots[..len];
    merged.sort_unstable_by(|a, b| {
        (a.point.cmp(&b.point))
            .then(b.probability.total_cmp(&a.probability))
            .then(a.keypoint.cmp(&b.keypoint))
    });
    let mut kept = 0;
    for i in 0..merged.len() {
        if kept == 0 || merged[i].point != merged[kept - 1].point {
            merged[kept] = merged[i];
            kept += 1;
        }
    }
    merged[..kept].sort_unstable_by_key(|c| c.keypoint);
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_keypoint_and_each_point_appear_once_with_their_best_match() {
        let mut slots = [Correspondence::EMPTY; 5];
        clear(&mut slots);
        keep_best(&mut slots[0], 7, 0.6, 0);
        keep_best(&mut slots[0], 8, 0.5, 1); // less probable: ignored
        keep_best(&mut slots[1], 7, 0.9, 1); // point 7 goes to keypoint 1
        keep_best(&mut slots[3], 9, 0.4, 2);
        keep_best(&mut slots[4], 9, 0.4, 0); // tie: the lower keypoint keeps point 9
        let kept = merge(&mut slots);
        assert_eq!(kept, 2);
        let pair = |c: &Correspondence| (c.keypoint, c.point, c.view);
        assert_eq!(pair(&slots[0]), (1, 7, 1));
        assert_eq!(pair(&slots[1]), (3, 9, 2));
    }

    #[test]
    fn the_digest_sees_a_one_ulp_change() {
        let c = Correspondence {
            keypoint: 3,
            point: 7,
            probability: 0.75,
            view: 1,
            inlier: true,
        };
        let next = Correspondence {
            probability: f32::from_bits(0.75f32.to_bits() + 1),
            ..c
        };
        assert_eq!(digest(&[]), 0x811c_9dc5);
        assert_eq!(digest(&[c, c]), digest(&[c, c]));
        assert_ne!(digest(&[c]), digest(&[next]));
        assert_ne!(digest(&[c, next]), digest(&[next, c]));
    }
}
