//! [`CalibFilter`]: the rolling-shutter MSCKF of seed chapter 4 (`VI_NOTES.md` §3, Table 4.1
//! of the seed): IMU samples in, frames of `(track, pixel)` observations in, the state and
//! calibration with 1σ out. No threads, IO or clocks.
//!
//! Per frame ([`CalibFilter::add_frame`]):
//! 1. propagate to `τ_j = t_mid,j + t̂_d` ([`super::propagate`]) and clone `(R, p, v)` with
//!    `P ← [P, P Jᵀ; J P, J P Jᵀ]` (§3 "Augmentation"), storing `t̂_d,j`;
//! 2. record the observations; the features to use are the tracks that ended (not seen in
//!    this frame) and, when the window is over [`CalibParams::max_clones`], the tracks seen
//!    by the oldest clone (§3: "features of clones about to leave"); a used track's stored
//!    observations are dropped, so no measurement is used twice;
//! 3. per feature: triangulate ([`super::triangulate`]), predict each observation at its row
//!    time ([`super::measure`]), project on the null space of `H_f`, χ² gate;
//!    stack, compress, EKF update ([`super::update`]) and retract;
//! 4. drop the oldest clone past the cap (the 2007 paper drops a third, evenly spaced; we
//!    drop the oldest, one per frame, after using its features).

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{DMatrix, DVector, Vector2};

use super::integrate::segments;
use super::params::{CalibEstimate, CalibParams, CalibPriors};
use super::propagate::{propagate_step, FirstEstimates, Transition};
use super::state::{clone_offset, CalibState, CloneState};
use super::update::{
    chi2_95, compress, joseph_in_place, kalman_gain, mahalanobis, residual_cost, stack,
    PriorMetric, Projected,
};
use super::{ImuSample, Observation, TrackId, CLONE_DIM, CORE_DIM, IDX_TD};

/// One feature's observations: (clone id, pixel).
type Track = Vec<(u64, Vector2<f64>)>;

/// Most halvings of a large iterated-EKF step before the update is refused.
pub const LINE_SEARCH_HALVINGS: usize = 3;

/// Errors of [`CalibFilter`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibError {
    /// The frame's clone time lies before the filter's time (frames out of order).
    #[error("frame clone time {tau_ns} ns is before the filter time {state_ns} ns")]
    FrameBeforeState {
        /// The frame's clone time `t_mid + t̂_d`.
        tau_ns: i64,
        /// The filter's time.
        state_ns: i64,
    },
    /// The IMU samples do not reach the time the filter must propagate to.
    #[error("IMU samples end at {last_ns:?} ns, before {need_ns} ns")]
    ImuNotCovering {
        /// Time of the last sample, if any.
        last_ns: Option<i64>,
        /// The time needed.
        need_ns: i64,
    },
}

/// What one frame did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameReport {
    /// Features whose rows went into the update.
    pub used: usize,
    /// Features rejected by the χ² gate.
    pub gated: usize,
    /// Features that failed triangulation or prediction.
    pub failed: usize,
    /// Of the used features, those fitted with the depth prior (too little parallax;
    /// [`CalibParams::depth_prior`]).
    pub low_parallax: usize,
    /// Rows of the update after compression.
    pub rows: usize,
    /// The iterated update could not lower its cost from the prior: nothing was applied
    /// (the features were used up all the same).
    pub refused: bool,
}

/// The rolling-shutter MSCKF with online calibration.
#[derive(Debug, Clone)]
pub struct CalibFilter {
    pub(super) params: CalibParams,
    priors: CalibPriors,
    start: CalibState,
    pub(super) state: CalibState,
    fej: FirstEstimates,
    pub(super) p: DMatrix<f64>,
    pub(super) clones: VecDeque<CloneState>,
    tracks: BTreeMap<TrackId, Track>,
    pub(super) imu: Vec<ImuSample>,
    next_clone: u64,
}

impl CalibFilter {
    /// A filter at `initial` (its `t_ns` is the start time) with the diagonal prior of
    /// `priors`.
    pub fn new(params: CalibParams, priors: CalibPriors, initial: CalibState) -> Self {
        Self {
            params,
            priors,
            fej: FirstEstimates::of(&initial.nav),
            start: initial,
            state: initial,
            p: priors.covariance(),
            clones: VecDeque::new(),
            tracks: BTreeMap::new(),
            imu: Vec::new(),
            next_clone: 0,
        }
    }

    /// Buffers one IMU sample (samples must come in time order; an older one is ignored).
    /// The filter propagates lazily, in [`CalibFilter::add_frame`]. Push the samples up to
    /// the frame's last row (`t_mid + t_d + t_r/2`) before the frame.
    pub fn push_imu(&mut self, sample: ImuSample) {
        if self.imu.last().is_none_or(|l| sample.t_ns > l.t_ns) {
            self.imu.push(sample);
        }
    }

    /// The prior σ it started with (e.g. after an initialisation, tighter than the
    /// configured ones: whether a σ shrank is judged against these).
    pub fn priors(&self) -> &CalibPriors {
        &self.priors
    }

    /// The state the filter started from, and its prior as an estimate (value, 1σ).
    pub fn start(&self) -> (&CalibState, CalibEstimate) {
        let p0 = self.priors.covariance();
        (&self.start, CalibEstimate::from_state(&self.start, &p0))
    }

    /// The current nominal state.
    pub fn state(&self) -> &CalibState {
        &self.state
    }

    /// The full covariance (core then clones, oldest first).
    pub fn covariance(&self) -> &DMatrix<f64> {
        &self.p
    }

    /// The clones in the window, oldest first.
    pub fn clones(&self) -> &VecDeque<CloneState> {
        &self.clones
    }

    /// Every calibration parameter with its 1σ.
    pub fn estimate(&self) -> CalibEstimate {
        CalibEstimate::from_state(&self.state, &self.p)
    }

    /// Propagates state and covariance to `t_ns` with the buffered samples.
    pub fn propagate_to(&mut self, t_ns: i64) -> Result<(), CalibError> {
        if t_ns < self.state.t_ns {
            return Err(CalibError::FrameBeforeState {
                tau_ns: t_ns,
                state_ns: self.state.t_ns,
            });
        }
        let last_ns = self.imu.last().map(|s| s.t_ns);
        let covered = self.imu.first().is_some_and(|f| f.t_ns <= self.state.t_ns);
        if !covered || last_ns.is_none_or(|l| l < t_ns) {
            return Err(CalibError::ImuNotCovering {
                last_ns,
                need_ns: t_ns,
            });
        }
        let segs = segments(&self.imu, self.state.t_ns as f64, t_ns as f64).ok_or(
            CalibError::ImuNotCovering {
                last_ns,
                need_ns: t_ns,
            },
        )?;
        for (dt, g, a) in segs {
            let tr = propagate_step(
                &mut self.state,
                &mut self.fej,
                &g,
                &a,
                dt,
                &self.params.imu_noise,
            );
            apply_transition(&mut self.p, &tr);
            self.p[(IDX_TD, IDX_TD)] += self.params.t_d_random_walk.powi(2) * dt;
        }
        self.state.t_ns = t_ns;
        Ok(())
    }

    /// Processes one frame: `t_mid_ns` is its middle-row stamp (camera clock with the prior
    /// `t_d0` applied, `VI_NOTES.md` §1), `obs` its feature observations.
    pub fn add_frame(
        &mut self,
        t_mid_ns: i64,
        obs: &[Observation],
    ) -> Result<FrameReport, CalibError> {
        let tau = t_mid_ns + (self.state.t_d * 1e9).round() as i64;
        self.propagate_to(tau)?;
        self.augment(tau);
        let id = self.clones.back().map_or(0, |c| c.id);
        for o in obs {
            self.tracks.entry(o.track).or_default().push((id, o.uv));
        }
        let features = self.select_features(id);
        let report = self.update(&features);
        if self.clones.len() > self.params.max_clones {
            self.drop_oldest();
        }
        self.prune_imu();
        Ok(report)
    }

    /// Appends the clone of the current body state at `tau_ns` (§3 "Augmentation").
    fn augment(&mut self, tau_ns: i64) {
        let n = self.p.nrows();
        let mut big = DMatrix::zeros(n + CLONE_DIM, n + CLONE_DIM);
        big.view_mut((0, 0), (n, n)).copy_from(&self.p);
        big.view_mut((n, 0), (CLONE_DIM, n))
            .copy_from(&self.p.rows(0, CLONE_DIM));
        big.view_mut((0, n), (n, CLONE_DIM))
            .copy_from(&self.p.columns(0, CLONE_DIM));
        big.view_mut((n, n), (CLONE_DIM, CLONE_DIM))
            .copy_from(&self.p.view((0, 0), (CLONE_DIM, CLONE_DIM)));
        self.p = big;
        self.clones.push_back(CloneState {
            id: self.next_clone,
            tau_ns,
            t_d_at_clone: self.state.t_d,
            nav: self.state.nav,
            p_fej: self.fej.p,
            v_fej: self.fej.v,
        });
        self.next_clone += 1;
    }

    /// Takes the tracks to use now out of the track table: ended ones (not seen by clone
    /// `current`) and, when the window is full, those seen by the oldest clone. Longest
    /// first, at most [`CalibParams::max_features_per_update`].
    fn select_features(&mut self, current: u64) -> Vec<Track> {
        let oldest = (self.clones.len() > self.params.max_clones)
            .then(|| self.clones.front().map(|c| c.id))
            .flatten();
        let take: Vec<TrackId> = self
            .tracks
            .iter()
            .filter(|(_, o)| {
                let ended = o.last().is_some_and(|l| l.0 != current);
                ended || oldest.is_some_and(|id| o.first().is_some_and(|f| f.0 == id))
            })
            .map(|(t, _)| *t)
            .collect();
        let mut out: Vec<Track> = take
            .iter()
            .filter_map(|t| self.tracks.remove(t))
            .filter(|o| o.len() >= self.params.min_track_len.max(2))
            .collect();
        out.sort_by_key(|o| std::cmp::Reverse(o.len()));
        if self.params.max_features_per_update > 0 {
            out.truncate(self.params.max_features_per_update);
        }
        out
    }

    /// Uses the selected features: gate (at the prior), stack, compress, update, retract.
    /// Iterated EKF (Gauss-Newton on `‖x ⊟ x_0‖²_{P_0⁻¹} + Σ‖r(x)‖²/σ²`): while the
    /// correction is large ([`CalibParams::iterate_above_sigma`]), the features are
    /// re-triangulated and the rows relinearised at the iterate `x_i`, and
    /// `x_{i+1} = x_0 ⊞ K_i (r_i + H_i (x_i ⊟ x_0))` with `K_i` from the prior `P_0`. A large
    /// step is taken only if it lowers that cost with every feature still triangulated, else
    /// it is halved (up to [`LINE_SEARCH_HALVINGS`] times); when even the first step cannot
    /// lower it, the linearisation is not trusted and the update is refused (state and `P`
    /// untouched, [`FrameReport::refused`]). The covariance takes the gain of the last
    /// linearisation (Joseph form).
    fn update(&mut self, features: &[Track]) -> FrameReport {
        let sigma2 = self.params.pixel_sigma.powi(2);
        let (mut lin, kept, mut report) = self.gate(features, sigma2);
        if lin.is_empty() {
            return report;
        }
        let (x0, clones0) = (self.state, self.clones.clone());
        let sigma0: Vec<f64> = (0..CORE_DIM).map(|i| self.p[(i, i)].sqrt()).collect();
        let moved = |v: &DVector<f64>| {
            (0..CORE_DIM)
                .map(|i| v[i].abs() / sigma0[i].max(1e-300))
                .fold(0.0, f64::max)
        };
        let mut cost = residual_cost(&lin, sigma2);
        let mut at = DVector::zeros(self.p.nrows());
        let mut metric = None;
        let mut last = None;
        for _ in 0..self.params.max_iterations.max(1) {
            let m = compress(stack(&lin, self.p.nrows()));
            report.rows = m.r.len();
            let Some(k) = kalman_gain(&self.p, &m.h, sigma2) else {
                break;
            };
            let step = &k * (&m.r + &m.h * &at) - &at;
            let small = moved(&step) < self.params.iterate_above_sigma;
            if small || self.params.max_iterations <= 1 {
                at += step;
                last = Some((k, m.h));
                break;
            }
            let metric = match &metric {
                Some(m) => m,
                None => match PriorMetric::new(&self.p) {
                    Some(m) => metric.insert(m),
                    None => break,
                },
            };
            match self.line_search(&x0, &clones0, &kept, metric, &at, &step, cost) {
                Some((next, c, rows)) => (at, cost, lin) = (next, c, rows),
                None => break,
            }
            last = Some((k, m.h));
        }
        self.set_iterate(&x0, &clones0, &at);
        match last {
            Some((k, h)) => joseph_in_place(&mut self.p, &k, &h, sigma2),
            None => report.refused = true,
        }
        report
    }

    /// The χ² gate (at the prior): the projected rows of the features that pass, the
    /// features themselves, and the counts.
    fn gate(&self, features: &[Track], sigma2: f64) -> (Vec<Projected>, Vec<Track>, FrameReport) {
        let mut report = FrameReport::default();
        let (mut parts, mut kept) = (Vec::new(), Vec::new());
        for f in features {
            let Some((proj, low_parallax)) = self.feature_rows(f) else {
                report.failed += 1;
                continue;
            };
            match mahalanobis(&proj.h, &proj.r, &self.p, sigma2) {
                Some(d) if d <= chi2_95(proj.r.len()) => {
                    parts.push(proj);
                    kept.push(f.clone());
                    report.low_parallax += usize::from(low_parallax);
                }
                _ => report.gated += 1,
            }
        }
        report.used = parts.len();
        (parts, kept, report)
    }

    /// Backtracking along `step` from the iterate `x_0 ⊞ at`: the first `at + α step`
    /// (α = 1, ½, ¼, …) whose cost is below `cost` with every feature re-triangulated, with
    /// its cost and rows.
    #[allow(clippy::too_many_arguments)]
    fn line_search(
        &mut self,
        x0: &CalibState,
        clones0: &VecDeque<CloneState>,
        kept: &[Track],
        metric: &PriorMetric,
        at: &DVector<f64>,
        step: &DVector<f64>,
        cost: f64,
    ) -> Option<(DVector<f64>, f64, Vec<Projected>)> {
        let sigma2 = self.params.pixel_sigma.powi(2);
        let mut alpha = 1.0;
        for _ in 0..=LINE_SEARCH_HALVINGS {
            let next = at + step * alpha;
            self.set_iterate(x0, clones0, &next);
            let rows: Option<Vec<Projected>> = kept
                .iter()
                .map(|f| self.feature_rows(f).map(|r| r.0))
                .collect();
            if let Some(rows) = rows {
                let c = metric.cost(&next) + residual_cost(&rows, sigma2);
                if c < cost {
                    return Some((next, c, rows));
                }
            }
            alpha *= 0.5;
        }
        None
    }

    /// Sets state and clones to `x_0 ⊞ e` (full error-state order).
    fn set_iterate(&mut self, x0: &CalibState, clones0: &VecDeque<CloneState>, e: &DVector<f64>) {
        self.state = *x0;
        self.clones.clone_from(clones0);
        self.retract_all(e);
    }

    /// Retracts the state and every clone by a full error-state vector.
    fn retract_all(&mut self, dx: &nalgebra::DVector<f64>) {
        self.state.retract(dx);
        for (i, c) in self.clones.iter_mut().enumerate() {
            c.nav.retract(dx, clone_offset(i));
        }
    }

    /// Removes the oldest clone from the state and its observations from the tracks.
    fn drop_oldest(&mut self) {
        let Some(old) = self.clones.pop_front() else {
            return;
        };
        let p = std::mem::replace(&mut self.p, DMatrix::zeros(0, 0));
        self.p = p
            .remove_rows(CORE_DIM, CLONE_DIM)
            .remove_columns(CORE_DIM, CLONE_DIM);
        self.tracks.retain(|_, o| {
            o.retain(|x| x.0 != old.id);
            !o.is_empty()
        });
    }

    /// Forgets IMU samples no row of a kept clone can need (keeps 0.2 s before the oldest).
    fn prune_imu(&mut self) {
        let keep_from = self.clones.front().map_or(self.state.t_ns, |c| c.tau_ns) - 200_000_000;
        let n = self.imu.partition_point(|s| s.t_ns < keep_from);
        if n > 1 {
            self.imu.drain(..n - 1);
        }
    }

    /// True when the covariance is symmetric and positive semi-definite (smallest
    /// eigenvalue ≥ -1e-12 of the largest). Right after a frame the newest clone duplicates
    /// the IMU state, so P is singular there by construction; propagation makes it definite.
    pub fn covariance_is_positive(&self) -> bool {
        let sym = (&self.p - self.p.transpose()).amax() <= 1e-12 * self.p.amax().max(1.0);
        let eig = self.p.clone().symmetric_eigenvalues();
        sym && eig.min() >= -1e-12 * eig.max().max(0.0)
    }
}

/// `P ← Φ P Φᵀ + Q` with Φ the identity outside the rows `dθ, dp, dv` (clones included).
fn apply_transition(p: &mut DMatrix<f64>, tr: &Transition) {
    let phi = DMatrix::from_column_slice(9, CORE_DIM, tr.phi.as_slice());
    let top = &phi * p.rows(0, CORE_DIM);
    p.rows_mut(0, 9).copy_from(&top);
    let left = p.columns(0, CORE_DIM) * phi.transpose();
    p.columns_mut(0, 9).copy_from(&left);
    for i in 0..9 {
        for j in 0..9 {
            p[(i, j)] += tr.q_nav[(i, j)];
        }
    }
    for k in 0..3 {
        p[(9 + k, 9 + k)] += tr.q_bias.0;
        p[(12 + k, 12 + k)] += tr.q_bias.1;
    }
    super::update::symmetrise(p);
}
