//! Sliding-window visual-inertial optimisation of the local mapper (issue 17; `VI_NOTES.md`
//! §4 "Local BA (Fig. 5.5)" and Table 5.1 "local BA = window poses, v, b, points vs
//! reprojections + IMU"): keyframe navigation states (pose, velocity, biases; 15-dof blocks
//! in the tangent order of [`NavState::retract`], `[δθ; δp; δv; δb_g; δb_a]`), map points,
//! robust reprojection factors, the preintegrated IMU factors of [`Preintegrated::residual`]
//! (15 rows: 9 preintegrated + 6 bias random walk) between consecutive keyframes and an
//! optional Gaussian prior on one keyframe's state.
//!
//! **Old states are fixed, not marginalised.** A keyframe with `fixed = true` keeps its state
//! but its factors stay: the keyframe just before the window is fixed *with its IMU factor*
//! to the first free keyframe, which anchors position, yaw, velocity, biases and, through the
//! IMU factor, gravity (roll/pitch); older covisible keyframes may be added fixed with their
//! observations only, without IMU factors ([`ViWindow::n_visual`]; ORB-SLAM3's local
//! inertial BA, Mur-Artal & Tardós 2017, `VI_NOTES.md` §4 Fig. 5.5, our proposal). Why not a marginalisation prior (OKVIS, VINS): (1) a Schur-complement
//! prior must stay at its linearisation point (first-estimate Jacobians) or it injects
//! spurious information along the 4 unobservable directions (x, y, z, yaw); fixing a state
//! adds none; (2) the prior becomes dense over every state it touches (the marginalised
//! keyframe's points tie it to most of the window), which breaks the keyframe-band sparsity
//! this solver is built on; (3) the local mapper runs on keyframes, not frames, so states
//! leaving the window have already been refined ~N times and fixing them costs little
//! accuracy. The price is that the window is over-confident about the fixed state (no
//! uncertainty flows from older keyframes). [`StatePrior`] is there for the ORB-SLAM3
//! variant that keeps a Gaussian prior (from the previous window) on the first free state,
//! or a bias prior; it is a plain Gaussian, not a marginal. The first window after the
//! inertial initialisation has no refined state to fix: leave every keyframe free and put
//! [`gauge_prior`] (position and yaw only, the 4 unobservable directions) on the first one,
//! so that the window also corrects the initialisation's gravity direction and scale
//! ([`states_from_init`], [`point_from_init`] map the initialisation into the window).
//! [`ViSolver::keyframe_covariance`] gives a keyframe's marginal covariance (consistency
//! checks, or a prior for the next window).
//!
//! **Factors.** Body `b` = IMU, world `w` gravity-aligned (`g = (0, 0, -9.81)`,
//! [`super::gravity_w`]); `t_bc` maps camera points to the body (`p_b = R_bc p_c + p_bc`,
//! the EuRoC `T_BS`):
//! ```text
//! reprojection (seed 2.57-2.60), row captured Δ after the keyframe (seed 2.61, rolling
//! shutter; Δ = 0 for a global shutter; the row's rotation is taken out of the keypoints):
//!   p_b = R_wbᵀ (p_w - p_wb - v_wb Δ),  p_c = R_bcᵀ (p_b - p_bc),
//!   r = (π(p_c) - z) / σ,   cost ρ_Huber(|r|²)
//!   ∂r/∂δθ = M [p_b]x,  ∂r/∂δp = -M R_wbᵀ,  ∂r/∂δv = -Δ M R_wbᵀ,  ∂r/∂p_w = M R_wbᵀ,
//!   M = ∂π/∂p_c R_bcᵀ / σ   (VI_NOTES §3: ∂z/∂dv_j = -Δ M)
//! IMU (Forster 2017, VI_NOTES §4): r = [r_R; r_v; r_p; r_bg; r_ba] of Preintegrated::residual,
//!   whitened by L⁻¹ with L Lᵀ = Preintegrated::residual_covariance (no robust kernel)
//! prior: r = [Log(R̄ᵀ R); p - p̄; v - v̄; b_g - b̄_g; b_a - b̄_a], cost rᵀ Ω r
//! ```
//!
//! **Solver.** Levenberg-Marquardt on `(H + λI) δ = -g`. The points are eliminated by the
//! Schur complement (each point's 3x3 block, damped by the same λ; the points couple the
//! `[θ; p; v]` corner of the keyframe blocks); the reduced keyframe system (15-dof blocks:
//! the IMU factors couple neighbours, co-observed points any pair) is
//! [`BlockSparseSystem`] with a dense LLᵀ for a window (≤ ~20 free keyframes), a sparse one
//! (block AMD ordering) beyond [`DENSE_MAX_KEYFRAMES`] free keyframes (a global BA). A point with
//! fewer than two valid observations in the window has no depth information and is held
//! fixed (its observation still constrains its keyframe). Keep one
//! [`ViSolver`] per thread: after the first call on a window of a given size, `optimize`
//! allocates nothing (the Jacobians of every factor go into reused buffers).
//!
//! **Several chains, several cameras** (the server's global visual-inertial BA, seed §5.4
//! "global BA = all"): the IMU-linked keyframes after [`ViWindow::n_visual`] may form several
//! chains, one after the other ([`ViWindow::chain_starts`]: no IMU factor into a chain's
//! first keyframe), e.g. one per client; each keyframe has its own camera and `t_bc`
//! ([`ViKeyframe::rig`]). A free keyframe without any IMU factor (a chain of one: a
//! monocular client's keyframe in a metric map) moves its pose only: its velocity and
//! biases, which nothing observes, are held by a stiff diagonal ([`UNLINKED_STIFFNESS`]).
//!
//! **Use in the local mapper** (per new keyframe, not per frame; `crate::vo::vi_window`
//! builds and writes back the window from the client map):
//! ```text
//! keyframes = [C_1 .. C_m fixed (n_visual = m, observations only),
//!              K_{n-N-1} fixed, K_{n-N} .. K_n free]   // N ≈ 10; the first window after the
//!                                                      // initialisation: all K free + gauge_prior
//! preints[k] = Preintegrated::from_window(imu, t_k, t_k+1, K_k.state.biases, params)
//!                                                      // re-integrated at the current biases
//! points/observations = the map points seen by the free keyframes (σ = 1.2^octave px)
//! report = solver.optimize(&mut window, &ViParams::default())?   // one ViSolver per thread
//! write back the free states and points_w; drop observations with χ² > 5.991
//! ```

use nalgebra::{Cholesky, Isometry3, Matrix2x3, Matrix3, Rotation3, SMatrix, Vector2, Vector3};

use super::init::InertialInit;
use super::preint::{Matrix15, NavState, Preintegrated, Vector15};
use crate::camera::PinholeRadtan;
use crate::lie::{skew, so3_jr_inv, so3_log};
use crate::optim::block_sparse::{BlockSparseSystem, Factorization};
use crate::optim::robust::RobustKernel;
use crate::CoreError;

/// 2x9 Jacobian of a reprojection w.r.t. a keyframe's `[δθ; δp; δv]` (the velocity moves
/// a rolling-shutter row's camera).
pub type Matrix2x9 = SMatrix<f64, 2, 9>;
type Matrix9 = SMatrix<f64, 9, 9>;
type Matrix9x3 = SMatrix<f64, 9, 3>;

/// Free keyframes up to which the reduced system is factorised densely (a local window);
/// beyond, sparsely after a block AMD ordering (a global BA).
pub const DENSE_MAX_KEYFRAMES: usize = 48;

/// Information put on the velocity and bias dimensions of a free keyframe without an IMU
/// factor (module docs, "Several chains"): nothing else observes them.
pub const UNLINKED_STIFFNESS: f64 = 1e8;

/// A keyframe of the window: its time and navigation state (IMU body in the gravity-aligned
/// world).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViKeyframe {
    /// Time, ns on the IMU clock.
    pub t_ns: i64,
    /// Pose, velocity and (effective) biases.
    pub state: NavState,
    /// Held constant (its factors still count); see the module docs.
    pub fixed: bool,
    /// Its camera and `t_bc`: 0 = [`ViWindow::camera`] and [`ViWindow::t_bc`], `r ≥ 1` =
    /// [`ViWindow::extra_rigs`]`[r - 1]`.
    pub rig: u16,
}

/// A camera and its camera-to-body transform (one per client in a global BA).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViRig {
    /// The camera model.
    pub camera: PinholeRadtan,
    /// Camera-to-body `T_bc`.
    pub t_bc: Isometry3<f64>,
}

/// One observation of a map point in a keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViObservation {
    /// Index into [`ViWindow::keyframes`].
    pub kf: u32,
    /// Index into [`ViWindow::points_w`].
    pub point: u32,
    /// Measured pixel (distorted image coordinates).
    pub uv: Vector2<f64>,
    /// Pixel standard deviation (e.g. `1.2^octave`), px.
    pub sigma_px: f64,
    /// Capture time of the pixel's row after the keyframe's time, s (rolling shutter, seed
    /// eq. 2.61; 0 for a global shutter).
    pub dt_s: f64,
}

/// A Gaussian prior on one keyframe's state, residual `[Log(R̄ᵀ R); p - p̄; v - v̄; b - b̄]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StatePrior {
    /// Index into [`ViWindow::keyframes`].
    pub kf: usize,
    /// The prior mean.
    pub mean: NavState,
    /// Information matrix (inverse covariance) in the tangent order `[θ; p; v; b_g; b_a]`.
    pub info: Matrix15,
}

/// The window's problem, plain data in and out; [`ViSolver::optimize`] updates the free
/// keyframe states and the points in place.
#[derive(Debug, Clone, PartialEq)]
pub struct ViWindow {
    /// Keyframes: the first [`ViWindow::n_visual`] with observations only, then the
    /// IMU-linked ones sorted by time.
    pub keyframes: Vec<ViKeyframe>,
    /// Keyframes at the start of [`ViWindow::keyframes`] without IMU factors (older
    /// covisible keyframes that only anchor the points; normally fixed).
    pub n_visual: usize,
    /// The IMU factors between consecutive keyframes after `n_visual`, in order, except into
    /// a chain's first keyframe ([`ViWindow::chain_starts`]): without extra chains
    /// `preints[k]` integrates from keyframe `n_visual + k` to `n_visual + k + 1`
    /// (`keyframes.len() - n_visual - 1 - chain_starts.len()` entries).
    pub preints: Vec<Preintegrated>,
    /// Indices (> `n_visual`, increasing) of keyframes that start a new IMU chain: no
    /// factor from the keyframe before (module docs, "Several chains"). Empty for a window.
    pub chain_starts: Vec<u32>,
    /// Map points in the world frame, m.
    pub points_w: Vec<Vector3<f64>>,
    /// Observations of the points in the keyframes.
    pub observations: Vec<ViObservation>,
    /// Camera-to-body transform `T_bc` (`p_b = T_bc p_c`).
    pub t_bc: Isometry3<f64>,
    /// The camera model.
    pub camera: PinholeRadtan,
    /// Cameras of keyframes with [`ViKeyframe::rig`] ≥ 1 (other clients').
    pub extra_rigs: Vec<ViRig>,
    /// Gravity in the world frame (e.g. [`super::gravity_w`]).
    pub gravity_w: Vector3<f64>,
    /// Optional Gaussian prior on one keyframe.
    pub prior: Option<StatePrior>,
}

impl ViWindow {
    /// An empty window (no keyframe; a placeholder camera and `t_bc`, set by whoever fills
    /// it), e.g. a buffer to fill again for each window.
    pub fn empty() -> Self {
        Self {
            keyframes: Vec::new(),
            n_visual: 0,
            preints: Vec::new(),
            chain_starts: Vec::new(),
            points_w: Vec::new(),
            observations: Vec::new(),
            t_bc: Isometry3::identity(),
            camera: PinholeRadtan::pinhole(1, 1, 1.0, 1.0, 0.0, 0.0),
            extra_rigs: Vec::new(),
            gravity_w: super::gravity_w(),
            prior: None,
        }
    }

    /// Whether every keyframe position and velocity and every point is finite (a solution
    /// fit to write back).
    pub fn is_finite(&self) -> bool {
        self.keyframes.iter().all(|kf| {
            let s = &kf.state;
            s.p.iter().chain(s.v.iter()).all(|x| x.is_finite())
        }) && self
            .points_w
            .iter()
            .all(|p| p.iter().all(|x| x.is_finite()))
    }

    /// The camera and `t_bc` of keyframe `kf` ([`ViKeyframe::rig`]; rig 0 when out of range).
    #[inline]
    pub fn rig(&self, kf: usize) -> (&PinholeRadtan, &Isometry3<f64>) {
        match self.keyframes.get(kf).map_or(0, |k| k.rig as usize) {
            0 => (&self.camera, &self.t_bc),
            r => self
                .extra_rigs
                .get(r - 1)
                .map_or((&self.camera, &self.t_bc), |x| (&x.camera, &x.t_bc)),
        }
    }
}

/// Settings of [`ViSolver::optimize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViParams {
    /// Largest number of accepted Levenberg-Marquardt iterations.
    pub max_iterations: usize,
    /// Robust kernel on the whitened reprojection χ² (ORB-SLAM: Huber δ = √5.991).
    pub kernel: RobustKernel,
    /// Initial damping λ (absolute, added to the diagonal).
    pub initial_lambda: f64,
    /// Stop when the relative cost decrease of an accepted step is below this.
    pub cost_tolerance: f64,
    /// Stop when the largest step component is below this.
    pub step_tolerance: f64,
    /// Observations of points closer than this to the camera (or behind it) are left out
    /// (counted in [`ViChi2::behind`]), m.
    pub min_depth_m: f64,
}

impl Default for ViParams {
    fn default() -> Self {
        Self {
            max_iterations: 20,
            kernel: RobustKernel::Huber {
                delta: 5.991f64.sqrt(),
            },
            initial_lambda: 1e-4,
            cost_tolerance: 1e-6,
            step_tolerance: 1e-8,
            min_depth_m: 0.05,
        }
    }
}

/// χ² of each factor family (whitened squared residuals, before the robust kernel).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ViChi2 {
    /// Reprojections (sum over observations in front of their camera).
    pub reprojection: f64,
    /// Reprojections above the 95 % χ²(2) gate 5.991.
    pub reprojection_outliers: usize,
    /// Observations behind their camera, closer than [`ViParams::min_depth_m`] or outside
    /// `|x/z|, |y/z| ≤ 2` (no residual).
    pub behind: usize,
    /// IMU preintegration rows (9 per factor).
    pub imu: f64,
    /// Bias random-walk rows (6 per factor).
    pub bias_walk: f64,
    /// The state prior.
    pub prior: f64,
    /// Total robust cost.
    pub cost: f64,
}

/// What [`ViSolver::optimize`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ViReport {
    /// Accepted iterations.
    pub iterations: usize,
    /// Linear solves (accepted and rejected steps).
    pub solves: usize,
    /// Factors at the start.
    pub initial: ViChi2,
    /// Factors at the end.
    pub last: ViChi2,
    /// Whether a tolerance was met (else the iteration or damping limit).
    pub converged: bool,
}

/// Reprojection of `p_w` in a body state with camera-to-body `t_bc`, in a row captured
/// `dt_s` after the state's time: the pixel, `∂uv/∂[δθ; δp; δv]` (2x9, [`NavState::retract`]
/// perturbation) and `∂uv/∂p_w` (module docs; unwhitened). `None` when the point is behind
/// the camera.
pub fn reprojection_jacobians(
    camera: &PinholeRadtan,
    t_bc: &Isometry3<f64>,
    state: &NavState,
    p_w: &Vector3<f64>,
    dt_s: f64,
) -> Option<(Vector2<f64>, Matrix2x9, Matrix2x3<f64>)> {
    let r_wb_t = state.r.matrix().transpose();
    let p_b = r_wb_t * (p_w - state.p - state.v * dt_s);
    let r_cb = t_bc.rotation.to_rotation_matrix().matrix().transpose();
    let p_c = r_cb * (p_b - t_bc.translation.vector);
    let (uv, d_uv_dpc) = camera.project_with_jacobian(&p_c)?;
    let m = d_uv_dpc * r_cb;
    let d_pw = m * r_wb_t;
    let mut d_x = Matrix2x9::zeros();
    d_x.fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(m * skew(&p_b)));
    d_x.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-d_pw));
    d_x.fixed_view_mut::<2, 3>(0, 6).copy_from(&(-d_pw * dt_s));
    Some((uv, d_x, d_pw))
}

/// The prior residual `[Log(R̄ᵀ R); p - p̄; v - v̄; b_g - b̄_g; b_a - b̄_a]` of `state` and its
/// Jacobian w.r.t. the state's tangent (block diagonal: `Jr⁻¹(r_θ)`, then identities).
pub fn prior_residual(mean: &NavState, state: &NavState) -> (Vector15, Matrix15) {
    let r_th = so3_log(&(mean.r.inverse() * state.r));
    let mut r = Vector15::zeros();
    r.fixed_rows_mut::<3>(0).copy_from(&r_th);
    r.fixed_rows_mut::<3>(3).copy_from(&(state.p - mean.p));
    r.fixed_rows_mut::<3>(6).copy_from(&(state.v - mean.v));
    r.fixed_rows_mut::<3>(9)
        .copy_from(&(state.biases.gyro - mean.biases.gyro));
    r.fixed_rows_mut::<3>(12)
        .copy_from(&(state.biases.accel - mean.biases.accel));
    let mut j = Matrix15::identity();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&so3_jr_inv(&r_th));
    (r, j)
}

/// The whitening `L⁻¹` of a preintegration's residual (`L Lᵀ` = its covariance, plus a floor
/// of 1e-14 on the diagonal so that noise-free settings stay invertible).
pub fn imu_sqrt_information(preint: &Preintegrated) -> Result<Matrix15, CoreError> {
    let cov = preint.residual_covariance() + Matrix15::identity() * 1e-14;
    let chol = Cholesky::new(cov).ok_or_else(|| {
        CoreError::Degenerate("vi window: IMU covariance not positive definite".into())
    })?;
    chol.l()
        .solve_lower_triangular(&Matrix15::identity())
        .ok_or_else(|| CoreError::Degenerate("vi window: IMU covariance singular".into()))
}

/// The keyframe states of a window started from the inertial initialisation
/// ([`super::init::initialize`]) of monocular keyframe poses `t_wc` (camera to the monocular
/// world, up to scale): in the gravity-aligned metric world `g`,
/// `R_gb = R_gw R_wc R_cb`, `p_gb = R_gw (s p_wc + R_wc p_cb)`, `v_gb = R_gw v_w`, the
/// initialisation's biases (`p_cb` = the body origin in the camera, `t_bc⁻¹`).
pub fn states_from_init(
    init: &InertialInit,
    t_wc: &[Isometry3<f64>],
    t_bc: &Isometry3<f64>,
) -> Vec<NavState> {
    let t_cb = t_bc.inverse();
    let r_cb = t_cb.rotation.to_rotation_matrix();
    t_wc.iter()
        .zip(&init.velocities_w)
        .map(|(t, v)| {
            let r_wc = t.rotation.to_rotation_matrix();
            NavState {
                r: init.r_gw * r_wc * r_cb,
                p: init.r_gw * (t.translation.vector * init.scale + r_wc * t_cb.translation.vector),
                v: init.r_gw * v,
                biases: init.biases,
            }
        })
        .collect()
}

/// A 4-DoF gauge prior for a window with no fixed keyframe (e.g. the first window after the
/// inertial initialisation): keyframe `kf`'s position (σ `sigma_p_m`) and yaw about world z
/// (σ `sigma_yaw_rad`) held near `state`, roll, pitch, velocity and biases free (only
/// position and yaw are unobservable, `VI_NOTES.md` §3). With the right perturbation
/// `R Exp(δθ)`, yaw is the body-frame direction `u = R_gbᵀ e_z`: `Ω_θ = u uᵀ / σ_yaw²`.
pub fn gauge_prior(kf: usize, state: &NavState, sigma_p_m: f64, sigma_yaw_rad: f64) -> StatePrior {
    let u = state.r.inverse() * Vector3::z();
    let mut info = Matrix15::zeros();
    info.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(u * u.transpose() / (sigma_yaw_rad * sigma_yaw_rad)));
    info.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(Matrix3::identity() / (sigma_p_m * sigma_p_m)));
    StatePrior {
        kf,
        mean: *state,
        info,
    }
}

/// A monocular map point in the gravity-aligned metric world of [`states_from_init`]:
/// `R_gw (s p_w)`.
pub fn point_from_init(init: &InertialInit, p_w: &Vector3<f64>) -> Vector3<f64> {
    init.r_gw * (p_w * init.scale)
}

/// A linearised reprojection (whitened, Huber weight applied through `w`).
#[derive(Debug, Clone, Copy, Default)]
struct ObsLin {
    valid: bool,
    w: f64,
    r: Vector2<f64>,
    j_x: Matrix2x9,
    j_p: Matrix2x3<f64>,
}

/// A linearised, whitened IMU factor.
#[derive(Debug, Clone, Copy, Default)]
struct ImuLin {
    r: Vector15,
    j_i: Matrix15,
    j_j: Matrix15,
}

/// The linearised factors at the current estimate.
#[derive(Debug, Default)]
struct Linearization {
    obs: Vec<ObsLin>,
    imu: Vec<ImuLin>,
    prior: (Vector15, Matrix15),
}

/// Reusable workspace of the window optimiser (one per thread).
#[derive(Debug)]
pub struct ViSolver {
    sys: BlockSparseSystem,
    pairs: Vec<(u32, u32)>,
    /// Variable block of each keyframe (`u32::MAX` = fixed).
    var_of_kf: Vec<u32>,
    /// The keyframe each IMU factor starts at (it ends at the next one).
    links: Vec<u32>,
    /// Whether each keyframe has an IMU factor.
    linked: Vec<bool>,
    /// Observations grouped by point: `obs_order[point_start[p]..point_start[p + 1]]`.
    obs_order: Vec<u32>,
    point_start: Vec<u32>,
    imu_sqrt_info: Vec<Matrix15>,
    lin: Linearization,
    /// The factors linearised at the candidate (swapped in when it is accepted).
    lin_cand: Linearization,
    cur_states: Vec<NavState>,
    /// Per point: `(V + λI)⁻¹`, `g_p` (gradient), and the step.
    v_inv: Vec<Matrix3<f64>>,
    g_p: Vec<Vector3<f64>>,
    dp: Vec<Vector3<f64>>,
    /// Per observation: `W = w J_xᵀ J_p` (6x3).
    w_blk: Vec<Matrix9x3>,
    cand_states: Vec<NavState>,
    cand_points: Vec<Vector3<f64>>,
}

impl Default for ViSolver {
    fn default() -> Self {
        Self::new()
    }
}

/// A zero navigation state (buffer filler).
fn zero_state() -> NavState {
    NavState {
        r: Rotation3::identity(),
        p: Vector3::zeros(),
        v: Vector3::zeros(),
        biases: Default::default(),
    }
}

impl ViSolver {
    /// An empty workspace.
    pub fn new() -> Self {
        Self {
            sys: BlockSparseSystem::new("vi window"),
            pairs: Vec::new(),
            var_of_kf: Vec::new(),
            links: Vec::new(),
            linked: Vec::new(),
            obs_order: Vec::new(),
            point_start: Vec::new(),
            imu_sqrt_info: Vec::new(),
            lin: Linearization::default(),
            lin_cand: Linearization::default(),
            cur_states: Vec::new(),
            v_inv: Vec::new(),
            g_p: Vec::new(),
            dp: Vec::new(),
            w_blk: Vec::new(),
            cand_states: Vec::new(),
            cand_points: Vec::new(),
        }
    }

    /// Optimises the free keyframe states and all points of `w` (Levenberg-Marquardt, module
    /// docs). Errors on inconsistent input (sizes, indices, no free keyframe) or a failed
    /// factorisation at the first step; `w` is only changed by accepted steps.
    pub fn optimize(&mut self, w: &mut ViWindow, p: &ViParams) -> Result<ViReport, CoreError> {
        self.setup(w)?;
        let mut report = ViReport::default();
        let mut chi = self.linearize(w, p);
        report.initial = chi;
        let mut lambda = p.initial_lambda.max(1e-12);
        'outer: while report.iterations < p.max_iterations {
            loop {
                report.solves += 1;
                let step_max = match self.solve_step(w, lambda) {
                    Ok(s) => s,
                    Err(e) => {
                        lambda *= 10.0;
                        if lambda > 1e12 {
                            if report.iterations == 0 {
                                return Err(e);
                            }
                            break 'outer;
                        }
                        continue;
                    }
                };
                self.make_candidate(w);
                let cand = self.evaluate_candidate(w, p);
                if cand.cost < chi.cost {
                    std::mem::swap(&mut self.cand_points, &mut w.points_w);
                    for (kf, s) in w.keyframes.iter_mut().zip(&self.cand_states) {
                        kf.state = *s;
                    }
                    report.iterations += 1;
                    let rel = (chi.cost - cand.cost) / chi.cost.max(1e-300);
                    std::mem::swap(&mut self.lin, &mut self.lin_cand);
                    chi = cand;
                    lambda = (lambda * 0.2).max(1e-12);
                    if rel < p.cost_tolerance || step_max < p.step_tolerance {
                        report.converged = true;
                        break 'outer;
                    }
                    break;
                }
                lambda *= 10.0;
                if lambda > 1e12 || step_max < p.step_tolerance {
                    report.converged = step_max < p.step_tolerance;
                    break 'outer;
                }
            }
        }
        report.last = chi;
        Ok(report)
    }

    /// Marginal covariance of keyframe `kf`'s state (tangent order `[θ; p; v; b_g; b_a]`)
    /// at the window's current estimate: the keyframe's 15x15 block of the inverse of the
    /// undamped Gauss-Newton information, points and the other free keyframes marginalised,
    /// the fixed keyframes taken as exact (robust weights of the current residuals
    /// included). A diagnostic (consistency checks) or the source of a [`StatePrior`]; it
    /// factorises the reduced system 15 times. Errors when `kf` is fixed or out of range or
    /// the information is singular.
    pub fn keyframe_covariance(
        &mut self,
        w: &ViWindow,
        p: &ViParams,
        kf: usize,
    ) -> Result<Matrix15, CoreError> {
        self.setup(w)?;
        let v = match self.var_of_kf.get(kf) {
            Some(&v) if v != u32::MAX => v as usize,
            _ => {
                return Err(CoreError::InvalidArgument(format!(
                    "vi window: keyframe {kf} is fixed or out of range"
                )))
            }
        };
        self.linearize(w, p);
        self.assemble_reduced(w, 0.0)?;
        let mut cov = Matrix15::zeros();
        for c in 0..15 {
            for i in 0..self.sys.n() {
                self.sys.rhs_mut(i, 0).fill(0.0);
            }
            self.sys.rhs_mut(v, 0)[c] = 1.0;
            self.sys.solve()?;
            cov.set_column(c, &self.sys.x_block::<15>(v));
        }
        Ok((cov + cov.transpose()) * 0.5)
    }

    /// Checks the window and prepares variables, the block pattern, the observation order
    /// and the IMU whitening. Allocates only when the window outgrows earlier ones.
    fn setup(&mut self, w: &ViWindow) -> Result<(), CoreError> {
        let (nk, np) = (w.keyframes.len(), w.points_w.len());
        let bad = |m: &str| Err(CoreError::InvalidArgument(format!("vi window: {m}")));
        if w.n_visual >= nk.max(1)
            || w.preints.len() + w.n_visual + 1 + w.chain_starts.len() != nk.max(1)
        {
            return bad("need one preintegration per consecutive keyframe pair of a chain");
        }
        if w.chain_starts.windows(2).any(|p| p[0] >= p[1])
            || w.chain_starts
                .iter()
                .any(|&c| c as usize <= w.n_visual || c as usize >= nk)
        {
            return bad("chain starts not increasing within the IMU-linked keyframes");
        }
        if w.keyframes
            .iter()
            .any(|k| k.rig as usize > w.extra_rigs.len())
        {
            return bad("keyframe rig out of range");
        }
        self.links.clear();
        self.linked.clear();
        self.linked.resize(nk, false);
        let mut starts = w.chain_starts.iter().peekable();
        for k in w.n_visual + 1..nk {
            if starts.next_if(|&&c| c as usize == k).is_none() {
                self.links.push(k as u32 - 1);
                self.linked[k - 1] = true;
                self.linked[k] = true;
            }
        }
        if w.observations.iter().any(|o| {
            o.kf as usize >= nk
                || o.point as usize >= np
                || o.sigma_px.is_nan()
                || o.sigma_px <= 0.0
        }) {
            return bad("observation index out of range or sigma <= 0");
        }
        if w.prior.is_some_and(|pr| pr.kf >= nk) {
            return bad("prior keyframe out of range");
        }
        self.var_of_kf.clear();
        let mut n_var = 0u32;
        for kf in &w.keyframes {
            self.var_of_kf.push(if kf.fixed { u32::MAX } else { n_var });
            n_var += u32::from(!kf.fixed);
        }
        if n_var == 0 {
            return bad("no free keyframe");
        }
        // Observations grouped by point (counting sort).
        self.point_start.clear();
        self.point_start.resize(np + 1, 0);
        for o in &w.observations {
            self.point_start[o.point as usize + 1] += 1;
        }
        for i in 0..np {
            self.point_start[i + 1] += self.point_start[i];
        }
        self.obs_order.clear();
        self.obs_order.resize(w.observations.len(), 0);
        self.dp.clear();
        self.dp.resize(np, Vector3::zeros());
        for (k, o) in w.observations.iter().enumerate() {
            // `dp` as a scratch cursor (x component) while sorting.
            let c = &mut self.dp[o.point as usize].x;
            self.obs_order[self.point_start[o.point as usize] as usize + *c as usize] = k as u32;
            *c += 1.0;
        }
        // Pattern: IMU neighbours and co-observing keyframes.
        self.pairs.clear();
        for &k in &self.links {
            let (a, b) = (self.var_of_kf[k as usize], self.var_of_kf[k as usize + 1]);
            if a != u32::MAX && b != u32::MAX {
                self.pairs.push((a, b));
            }
        }
        for pt in 0..np {
            let obs =
                &self.obs_order[self.point_start[pt] as usize..self.point_start[pt + 1] as usize];
            for (x, &oa) in obs.iter().enumerate() {
                let a = self.var_of_kf[w.observations[oa as usize].kf as usize];
                for &ob in &obs[x + 1..] {
                    let b = self.var_of_kf[w.observations[ob as usize].kf as usize];
                    if a != u32::MAX && b != u32::MAX && a != b {
                        self.pairs.push((a, b));
                    }
                }
            }
        }
        let factorization = if n_var as usize <= DENSE_MAX_KEYFRAMES {
            Factorization::Dense
        } else {
            Factorization::SparseBlockAmd
        };
        self.sys
            .setup_uniform(n_var as usize, 15, 1, &mut self.pairs, factorization)?;
        self.imu_sqrt_info.clear();
        for pre in &w.preints {
            self.imu_sqrt_info.push(imu_sqrt_information(pre)?);
        }
        let no = w.observations.len();
        self.lin.obs.resize(no, ObsLin::default());
        self.lin_cand.obs.resize(no, ObsLin::default());
        self.lin_cand.imu.resize(w.preints.len(), ImuLin::default());
        self.w_blk.resize(no, Matrix9x3::zeros());
        self.lin.imu.resize(w.preints.len(), ImuLin::default());
        self.v_inv.resize(np, Matrix3::zeros());
        self.g_p.resize(np, Vector3::zeros());
        self.cand_states.resize(nk, zero_state());
        self.cur_states.resize(nk, zero_state());
        self.cand_points.resize(np, Vector3::zeros());
        Ok(())
    }
}

#[path = "window_solve.rs"]
mod solve;

#[cfg(test)]
#[path = "window_tests.rs"]
pub(crate) mod tests;
