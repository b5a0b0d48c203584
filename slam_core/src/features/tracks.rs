//! Feature tracks across consecutive frames: the image front end of the calibration filter
//! (issue 18; `VI_NOTES.md` §3 "Features"), which needs each feature's pixel in every frame
//! that saw it, with an identity that lasts, and no map.
//!
//! Each frame's ORB features are matched to the active tracks in a window around where the
//! caller predicts them (the gyro's rotation between the frames, through a guess of the
//! intrinsics: the window absorbs the guess's error), with the distance, ratio, uniqueness
//! and rotation-consistency rules of [`match_two_frames_windowed`]. A matched feature
//! continues its track ([`TrackId`], descriptor and position updated); any other starts a
//! new one. A track missed in a frame (ORB does not re-detect every corner) stays active at
//! its predicted position for up to [`TrackerParams::max_missed`] frames. Outliers that pass
//! are left to the filter's χ² gate.
use super::{
    match_two_frames_windowed, FeatureGrid, Match, MatchParams, OrbFeatures, WindowMatchParams,
};
use crate::CoreError;

pub use crate::ids::TrackId;

/// One feature of a frame with its track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedPoint {
    /// Its track.
    pub id: TrackId,
    /// Pixel `[u, v]`, level 0.
    pub uv: [f32; 2],
    /// Frames of its track so far, this one included (1 = a new track).
    pub length: u32,
}

/// Settings of [`FeatureTracker`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerParams {
    /// The matching rules; `radius` is the window's half-size around the prediction.
    pub matching: WindowMatchParams,
    /// Cell size of the feature grid, pixels.
    pub grid_cell_px: f32,
    /// Frames in a row a track may be missed before it ends.
    pub max_missed: u32,
}

impl Default for TrackerParams {
    fn default() -> Self {
        Self {
            matching: WindowMatchParams {
                accept: MatchParams {
                    max_distance: 50,
                    ratio: 0.8,
                    unique: true,
                },
                radius: 24.0,
                max_octave: u8::MAX,
                octave_tolerance: 1,
                rotation_bins: 30,
            },
            grid_cell_px: 32.0,
            max_missed: 3,
        }
    }
}

/// What a track carries besides its last feature.
#[derive(Debug, Clone, Copy, PartialEq)]
struct TrackState {
    id: TrackId,
    length: u32,
    missed: u32,
}

/// Tracks features from frame to frame (module docs). Buffers are kept between frames.
#[derive(Debug, Clone)]
pub struct FeatureTracker {
    params: TrackerParams,
    width: f32,
    height: f32,
    /// The active tracks' last features (at their predicted position when missed).
    active: OrbFeatures,
    states: Vec<TrackState>,
    next_active: OrbFeatures,
    next_states: Vec<TrackState>,
    /// Track of each feature of the current frame (`None`: a new track).
    matched: Vec<Option<usize>>,
    grid: FeatureGrid,
    predicted: Vec<[f32; 2]>,
    matches: Vec<Match>,
    next_id: u64,
}

impl FeatureTracker {
    /// A tracker for `width` x `height` frames.
    pub fn new(params: TrackerParams, width: usize, height: usize) -> Result<Self, CoreError> {
        Ok(Self {
            params,
            width: width as f32,
            height: height as f32,
            active: OrbFeatures::with_capacity(0),
            states: Vec::new(),
            next_active: OrbFeatures::with_capacity(0),
            next_states: Vec::new(),
            matched: Vec::new(),
            grid: FeatureGrid::new(width, height, params.grid_cell_px)?,
            predicted: Vec::new(),
            matches: Vec::new(),
            next_id: 0,
        })
    }

    /// Gives the features of the next frame their tracks, written to `out` (one per feature,
    /// in the order of `current`). `predict` maps a pixel of the previous frame to where it
    /// is expected in this one.
    pub fn track(
        &mut self,
        current: &OrbFeatures,
        predict: impl Fn([f32; 2]) -> [f32; 2],
        out: &mut Vec<TrackedPoint>,
    ) -> Result<(), CoreError> {
        self.grid.build(&current.keypoints);
        self.predicted.clear();
        self.predicted
            .extend(self.active.keypoints.iter().map(|k| predict([k.x, k.y])));
        match_two_frames_windowed(
            &self.active,
            current,
            &self.grid,
            Some(&self.predicted),
            &self.params.matching,
            &mut self.matches,
        )?;
        self.matched.clear();
        self.matched.resize(current.len(), None);
        for m in &self.matches {
            self.matched[m.train as usize] = Some(m.query as usize);
        }
        self.next_active.clear();
        self.next_states.clear();
        out.clear();
        for (i, (k, d)) in current
            .keypoints
            .iter()
            .zip(&current.descriptors)
            .enumerate()
        {
            let state = match self.matched[i] {
                Some(t) => TrackState {
                    length: self.states[t].length + 1,
                    missed: 0,
                    ..self.states[t]
                },
                None => {
                    self.next_id += 1;
                    TrackState {
                        id: TrackId(self.next_id - 1),
                        length: 1,
                        missed: 0,
                    }
                }
            };
            out.push(TrackedPoint {
                id: state.id,
                uv: [k.x, k.y],
                length: state.length,
            });
            self.next_active.keypoints.push(*k);
            self.next_active.descriptors.push(*d);
            self.next_states.push(state);
        }
        self.keep_missed_tracks();
        self.next_active.scale.clone_from(&current.scale);
        std::mem::swap(&mut self.active, &mut self.next_active);
        std::mem::swap(&mut self.states, &mut self.next_states);
        Ok(())
    }

    /// Carries the active tracks no feature continued into the next frame's set, at their
    /// predicted position, while they were missed less than `max_missed` frames in a row and
    /// stay in the image.
    fn keep_missed_tracks(&mut self) {
        let mut continued = std::mem::take(&mut self.matches);
        continued.sort_unstable_by_key(|m| m.query);
        let mut c = continued.iter().peekable();
        for (t, state) in self.states.iter().enumerate() {
            if c.next_if(|m| m.query as usize == t).is_some() {
                continue;
            }
            let [x, y] = self.predicted[t];
            let inside = x >= 0.0 && y >= 0.0 && x < self.width && y < self.height;
            if state.missed >= self.params.max_missed || !inside {
                continue;
            }
            let mut k = self.active.keypoints[t];
            (k.x, k.y) = (x, y);
            self.next_active.keypoints.push(k);
            self.next_active
                .descriptors
                .push(self.active.descriptors[t]);
            self.next_states.push(TrackState {
                missed: state.missed + 1,
                ..*state
            });
        }
        self.matches = continued;
    }
}
