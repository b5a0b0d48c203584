//! When a tracked frame becomes a keyframe (seed §3.3): it must track more than 15 map
//! points, and either fewer than 90% of the points of its reference keyframe (the keyframe
//! sharing most points with it) or fewer than 200 points in absolute terms. As in ORB-SLAM,
//! a minimum and maximum number of frames between keyframes keep the rate sane.

/// Parameters of the keyframe rule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeRuleParams {
    /// A keyframe needs more than this many tracked points (seed: 15).
    pub min_tracked: usize,
    /// Fewer tracked points than this always asks for a keyframe (seed: 200).
    pub few_tracked: usize,
    /// Fraction of the reference keyframe's points below which a keyframe is made (0.9).
    pub ref_ratio: f64,
    /// At least this many frames since the last keyframe (0 = no limit).
    pub min_frames: u32,
    /// A keyframe at the latest after this many frames (0 = no limit), if tracking is fine.
    pub max_frames: u32,
}

impl Default for KeyframeRuleParams {
    fn default() -> Self {
        Self {
            min_tracked: 15,
            few_tracked: 200,
            ref_ratio: 0.9,
            min_frames: 0,
            max_frames: 20,
        }
    }
}

/// The keyframe decision.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct KeyframeRule {
    /// Parameters.
    pub params: KeyframeRuleParams,
}

impl KeyframeRule {
    /// Should the current frame become a keyframe? `tracked`: map points matched in this
    /// frame (inliers); `ref_tracked`: points of the reference keyframe (seen by ≥ 2
    /// keyframes, or all in a young map); `frames_since_kf`: frames since the last keyframe;
    /// `mapping_idle`: local mapping has no keyframe waiting.
    ///
    /// As in ORB-SLAM, a keyframe the seed's rule asks for is only made when local mapping
    /// is idle (or `max_frames` have passed), so that keyframes come no faster than they can
    /// be mapped.
    pub fn needs_keyframe(
        &self,
        tracked: usize,
        ref_tracked: usize,
        frames_since_kf: u32,
        mapping_idle: bool,
    ) -> bool {
        let p = &self.params;
        if tracked <= p.min_tracked || frames_since_kf < p.min_frames {
            return false;
        }
        let overdue = p.max_frames > 0 && frames_since_kf >= p.max_frames;
        let weak = (tracked as f64) < p.ref_ratio * ref_tracked as f64 || tracked < p.few_tracked;
        (weak && mapping_idle) || overdue
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seed_rule() {
        let r = KeyframeRule::default();
        assert!(
            !r.needs_keyframe(15, 1000, 5, true),
            "needs more than 15 points"
        );
        assert!(r.needs_keyframe(100, 120, 1, true), "fewer than 200 points");
        assert!(
            r.needs_keyframe(400, 500, 1, true),
            "fewer than 90% of the reference"
        );
        assert!(
            !r.needs_keyframe(480, 500, 1, true),
            "still 96% of the reference"
        );
        assert!(
            r.needs_keyframe(480, 500, 20, true),
            "max frames between keyframes"
        );
        assert!(
            !r.needs_keyframe(100, 120, 1, false),
            "local mapping busy: wait"
        );
        assert!(
            r.needs_keyframe(480, 500, 20, false),
            "overdue even when busy"
        );
    }
}
