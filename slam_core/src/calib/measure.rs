//! One observation predicted at its own row time and its Jacobians (`VI_NOTES.md` §3
//! "Features" and "Measurement in row v of image j"; Li, Kim & Mourikis, ICRA 2013).
//!
//! A feature is `(α, β, ρ)` in its anchor camera `C_a` (the camera of clone `a` at the
//! clone's time `τ_a`): `p^Ca = (α, β, 1)/ρ`,
//! `p^g_f = p_a + R_a R_cbᵀ (p^Ca - p_cb)`. Row `v` of image j is taken
//! `Δ = (t̂_d - t̂_d,j) + (v/N - ½) t̂_r` after the clone; its body state `(R̂, p̂, v̂, ω̂)` is
//! integrated from the clone ([`super::integrate`]). Then
//! `p^b = R̂ᵀ (p^g_f - p̂)`, `p^c = R_cb p^b + p_cb`, `z = π(p^c)`.
//!
//! To first order `dp(τ+Δ) = dp_j + Δ dv_j`, `dθ(τ+Δ) = dθ_j + R̂ Jr(ω̂Δ) Δ δω`, where `δω` is
//! the error of the corrected rate (biases, `T_g`, `T_s`, `T_a`); the position terms of
//! the IMU errors over Δ (≤ ~t_r/2 + |t_d error|) are dropped. With `J_π = ∂z/∂p^c`,
//! `M = J_π R_cb R̂ᵀ`:
//! ```text
//! ∂z/∂dθ_j = M [p^g_f - p̂]x   ∂z/∂dp_j = -M   ∂z/∂dv_j = -Δ M
//! ∂z/∂t_d  = J_π R_cb ([p^b]x ω̂ - R̂ᵀ v̂)   ∂z/∂t_r = (v/N - ½) ∂z/∂t_d
//! ∂z/∂p_cb = J_π (I - R_cb R̂ᵀ R_a R_cbᵀ)
//! ∂z/∂dθ_a = -M [p^g_f - p̂_a]x   ∂z/∂dp_a = M
//! ∂z/∂(α,β,ρ) = M R_a R_cbᵀ [e1/ρ, e2/ρ, -(α,β,1)/ρ²]
//! ∂z/∂δω   = M [p^g_f - p̂]x R̂ Jr(ω̂Δ) Δ
//! ```
//! and the pinhole and distortion columns of [`PinholeRadtan::pinhole_jacobian`] and
//! [`PinholeRadtan::distortion_jacobian`]. The `δω` row keeps a gyro-bias error
//! (0.01 rad/s ≈ 0.7 % of a 1.5 rad/s rate) from being read as readout time. With FEJ the
//! positions inside the `dθ` columns are the clones' first estimates
//! (`p̂ ≈ p_j,fej + Δ v_j,fej`, `p̂_a = p_a,fej`), so that a global yaw moves no residual
//! (the filter's consistency, §3 "Observability").

use nalgebra::{Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};

use super::state::{CalibState, NavState};
use super::CAM_BLOCK;
use crate::camera::PinholeRadtan;
use crate::lie::{skew, so3_jr};

/// A feature in anchored inverse depth: `p^Ca = (α, β, 1)/ρ`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InvDepth {
    /// `x/z` in the anchor camera.
    pub alpha: f64,
    /// `y/z` in the anchor camera.
    pub beta: f64,
    /// `1/z` in the anchor camera, 1/m.
    pub rho: f64,
}

/// The body state at an observation's row time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowPose {
    /// `(R̂, p̂, v̂)` at `τ_j + Δ`.
    pub nav: NavState,
    /// Corrected body rate there, rad/s.
    pub omega_b: Vector3<f64>,
    /// Corrected specific force there, m/s² (for the rate Jacobian's `T_s` and `b_a` terms).
    pub accel_b: Vector3<f64>,
    /// `Δ`, s.
    pub delta: f64,
    /// Where the observed pixel lies in the readout, `-½ .. ½` (`v/N - ½` for rows top to
    /// bottom; [`PinholeRadtan::readout_fraction`]).
    pub shutter: f64,
    /// Linearisation point of the position in the `dθ_j` column (FEJ or `nav.p_gb`).
    pub p_lin: Vector3<f64>,
}

/// The anchor clone's pose (and the position its `dθ_a` column is linearised at).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorPose {
    /// The anchor clone's body state.
    pub nav: NavState,
    /// Linearisation point of the position in the `dθ_a` column.
    pub p_lin: Vector3<f64>,
}

/// Prediction and Jacobians of one observation.
#[derive(Debug, Clone, PartialEq)]
pub struct ObsJacobians {
    /// Predicted pixel.
    pub z: Vector2<f64>,
    /// Columns of the observing clone `(dθ, dp, dv)`.
    pub h_clone: SMatrix<f64, 2, 9>,
    /// Columns of the anchor clone `(dθ, dp)` (its `dv` column is zero).
    pub h_anchor: SMatrix<f64, 2, 6>,
    /// Columns `p_cb, fx fy cx cy, k1 k2 p1 p2, t_d, t_r` (error-state order).
    pub h_cam: SMatrix<f64, 2, CAM_BLOCK>,
    /// Columns of `(α, β, ρ)`.
    pub h_f: Matrix2x3<f64>,
    /// `∂z/∂δω`: an error `δω` of the corrected rate over the row offset turns the row's
    /// attitude by `R̂ Jr(ω̂Δ) Δ δω`; chain with `∂ω/∂(b_g, T_g, T_s, b_a, T_a)`
    /// ([`super::propagate::rate_jacobians`]).
    pub h_omega: Matrix2x3<f64>,
}

/// The anchor camera's point `(α, β, 1)/ρ` in the global frame.
pub fn feature_in_world(state: &CalibState, anchor: &NavState, f: &InvDepth) -> Vector3<f64> {
    let p_ca = Vector3::new(f.alpha, f.beta, 1.0) / f.rho;
    anchor.p_gb + anchor.r_gb * (state.r_cb.inverse() * (p_ca - state.p_cb))
}

/// A global point in the camera at `nav`: `p^c = R_cb R̂ᵀ (p - p̂) + p_cb`.
pub fn world_to_camera(state: &CalibState, nav: &NavState, p_g: &Vector3<f64>) -> Vector3<f64> {
    state.r_cb * (nav.r_gb.inverse() * (p_g - nav.p_gb)) + state.p_cb
}

/// The predicted pixel only (no Jacobians); `None` behind the camera.
pub fn predict(
    state: &CalibState,
    row: &RowPose,
    anchor: &NavState,
    f: &InvDepth,
) -> Option<Vector2<f64>> {
    let p_g = feature_in_world(state, anchor, f);
    state
        .camera
        .project(&world_to_camera(state, &row.nav, &p_g))
}

/// Prediction and every Jacobian block of the module docs; `None` when the point is not in
/// front of the camera.
pub fn observe(
    state: &CalibState,
    row: &RowPose,
    anchor: &AnchorPose,
    f: &InvDepth,
) -> Option<ObsJacobians> {
    let cam: &PinholeRadtan = &state.camera;
    let r_cb = state.r_cb.into_inner();
    let r = row.nav.r_gb.into_inner();
    let r_a = anchor.nav.r_gb.into_inner();
    let p_f = feature_in_world(state, &anchor.nav, f);
    let p_b = r.transpose() * (p_f - row.nav.p_gb);
    let p_c = r_cb * p_b + state.p_cb;
    let (z, j_pi) = cam.project_with_jacobian(&p_c)?;
    let m = j_pi * r_cb * r.transpose();
    let mut h_clone = SMatrix::<f64, 2, 9>::zeros();
    h_clone
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(m * skew(&(p_f - row.p_lin))));
    h_clone.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-m));
    h_clone
        .fixed_view_mut::<2, 3>(0, 6)
        .copy_from(&(-m * row.delta));
    let mut h_anchor = SMatrix::<f64, 2, 6>::zeros();
    h_anchor
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(-m * skew(&(p_f - anchor.p_lin))));
    h_anchor.fixed_view_mut::<2, 3>(0, 3).copy_from(&m);
    let h_td = j_pi * r_cb * (skew(&p_b) * row.omega_b - r.transpose() * row.nav.v_gb);
    let r_cj_ca = r_cb * r.transpose() * r_a * r_cb.transpose();
    let mut h_cam = SMatrix::<f64, 2, CAM_BLOCK>::zeros();
    h_cam
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(j_pi * (Matrix3::identity() - r_cj_ca)));
    h_cam
        .fixed_view_mut::<2, 4>(0, 3)
        .copy_from(&cam.pinhole_jacobian(&p_c)?);
    h_cam
        .fixed_view_mut::<2, 4>(0, 7)
        .copy_from(&cam.distortion_jacobian(&p_c)?);
    h_cam.fixed_view_mut::<2, 1>(0, 11).copy_from(&h_td);
    h_cam
        .fixed_view_mut::<2, 1>(0, 12)
        .copy_from(&(h_td * row.shutter));
    let ir = 1.0 / f.rho;
    let d_pca = Matrix3::from_columns(&[
        Vector3::new(ir, 0.0, 0.0),
        Vector3::new(0.0, ir, 0.0),
        -Vector3::new(f.alpha, f.beta, 1.0) * (ir * ir),
    ]);
    let h_f = m * r_a * r_cb.transpose() * d_pca;
    let h_omega = m * skew(&(p_f - row.p_lin)) * r * so3_jr(&(row.omega_b * row.delta)) * row.delta;
    Some(ObsJacobians {
        z,
        h_clone,
        h_anchor,
        h_cam,
        h_f,
        h_omega,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::sim::test_state;
    use crate::calib::{CORE_DIM, IDX_PCB};
    use crate::lie::so3_exp;
    use nalgebra::{DVector, Rotation3};

    /// Row pose of a constant-rate, constant-velocity model from `clone`: the model the
    /// Jacobians are exact for (the filter integrates the IMU instead).
    fn row_of(
        state: &CalibState,
        clone: &NavState,
        t_d_clone: f64,
        shutter: f64,
        w: &Vector3<f64>,
    ) -> RowPose {
        let delta = (state.t_d - t_d_clone) + shutter * state.t_r;
        let nav = NavState {
            r_gb: clone.r_gb * so3_exp(&(w * delta)),
            p_gb: clone.p_gb + clone.v_gb * delta,
            v_gb: clone.v_gb,
        };
        RowPose {
            nav,
            omega_b: *w,
            accel_b: Vector3::zeros(),
            delta,
            shutter,
            p_lin: nav.p_gb,
        }
    }

    #[derive(Clone, Copy)]
    struct Case {
        state: CalibState,
        clone: NavState,
        anchor: NavState,
        f: InvDepth,
        w: Vector3<f64>,
        shutter: f64,
        t_d_clone: f64,
    }

    impl Case {
        fn new() -> Self {
            let state = test_state();
            let clone = NavState {
                r_gb: Rotation3::from_scaled_axis(Vector3::new(0.3, -0.2, 0.5)),
                p_gb: Vector3::new(0.4, -0.1, 0.2),
                v_gb: Vector3::new(0.8, -0.5, 0.3),
            };
            let anchor = NavState {
                r_gb: Rotation3::from_scaled_axis(Vector3::new(0.25, -0.1, 0.45)),
                p_gb: Vector3::new(0.2, 0.1, 0.15),
                v_gb: Vector3::zeros(),
            };
            let f = InvDepth {
                alpha: 0.15,
                beta: -0.1,
                rho: 0.4,
            };
            let w = Vector3::new(1.2, -0.7, 0.9);
            Self {
                state,
                clone,
                anchor,
                f,
                w,
                shutter: 0.3,
                t_d_clone: 0.004,
            }
        }

        fn z(&self) -> Vector2<f64> {
            let row = row_of(
                &self.state,
                &self.clone,
                self.t_d_clone,
                self.shutter,
                &self.w,
            );
            predict(&self.state, &row, &self.anchor, &self.f).unwrap()
        }

        fn jac(&self) -> ObsJacobians {
            let row = row_of(
                &self.state,
                &self.clone,
                self.t_d_clone,
                self.shutter,
                &self.w,
            );
            let anchor = AnchorPose {
                nav: self.anchor,
                p_lin: self.anchor.p_gb,
            };
            observe(&self.state, &row, &anchor, &self.f).unwrap()
        }
    }

    /// Central difference of `Case::z` under `perturb(case, ±h)`.
    fn fd(base: &Case, h: f64, perturb: impl Fn(&mut Case, f64)) -> Vector2<f64> {
        let mut plus = Case { ..*base };
        perturb(&mut plus, h);
        let mut minus = Case { ..*base };
        perturb(&mut minus, -h);
        (plus.z() - minus.z()) / (2.0 * h)
    }

    fn nav_dx(k: usize, h: f64) -> DVector<f64> {
        let mut dx = DVector::zeros(9);
        dx[k] = h;
        dx
    }

    fn close(num: &Vector2<f64>, ana: &Vector2<f64>, what: &str) {
        let err = (num - ana).norm();
        assert!(
            err < 1e-5 * (1.0 + num.norm()),
            "{what}: fd {num} vs {ana} ({err})"
        );
    }

    #[test]
    fn prediction_is_consistent_with_jacobian_call() {
        let c = Case::new();
        assert!((c.z() - c.jac().z).norm() < 1e-12);
    }

    #[test]
    fn clone_columns_match_finite_differences() {
        let c = Case::new();
        let j = c.jac();
        for k in 0..9 {
            let num = fd(&c, 1e-6, |c, h| c.clone.retract(&nav_dx(k, h), 0));
            close(&num, &j.h_clone.column(k).into(), &format!("clone {k}"));
        }
    }

    #[test]
    fn anchor_columns_match_finite_differences() {
        let c = Case::new();
        let j = c.jac();
        for k in 0..6 {
            let num = fd(&c, 1e-6, |c, h| c.anchor.retract(&nav_dx(k, h), 0));
            close(&num, &j.h_anchor.column(k).into(), &format!("anchor {k}"));
        }
        let num = fd(&c, 1e-6, |c, h| c.anchor.retract(&nav_dx(7, h), 0));
        assert!(num.norm() < 1e-9, "the anchor's velocity does not enter");
    }

    #[test]
    fn camera_columns_match_finite_differences() {
        let c = Case::new();
        let j = c.jac();
        for k in 0..CAM_BLOCK {
            let num = fd(&c, 1e-7, |c, h| {
                let mut dx = DVector::zeros(CORE_DIM);
                dx[IDX_PCB + k] = h;
                c.state.retract(&dx);
            });
            close(
                &num,
                &j.h_cam.column(k).into(),
                &format!("camera block {k}"),
            );
        }
    }

    #[test]
    fn feature_columns_match_finite_differences() {
        let c = Case::new();
        let j = c.jac();
        let cols: [fn(&mut InvDepth, f64); 3] =
            [|f, h| f.alpha += h, |f, h| f.beta += h, |f, h| f.rho += h];
        for (k, step) in cols.iter().enumerate() {
            let num = fd(&c, 1e-7, |c, h| step(&mut c.f, h));
            close(&num, &j.h_f.column(k).into(), &format!("feature {k}"));
        }
    }

    #[test]
    fn rate_columns_match_finite_differences() {
        let c = Case::new();
        let j = c.jac();
        for k in 0..3 {
            let num = fd(&c, 1e-6, |c, h| c.w[k] += h);
            // Perturbing ω also moves h_td's linearisation point, not the prediction: only the
            // attitude over Δ changes z.
            close(&num, &j.h_omega.column(k).into(), &format!("rate {k}"));
        }
    }

    #[test]
    fn anchor_equal_to_clone_adds_both_blocks() {
        let mut c = Case::new();
        c.anchor = c.clone;
        let j = c.jac();
        for k in 0..6 {
            let num = fd(&c, 1e-6, |c, h| {
                c.clone.retract(&nav_dx(k, h), 0);
                c.anchor.retract(&nav_dx(k, h), 0);
            });
            let ana: Vector2<f64> = j.h_clone.column(k) + j.h_anchor.column(k);
            close(&num, &ana, &format!("joint {k}"));
        }
    }

    #[test]
    fn time_offset_is_unobservable_at_rest() {
        let mut c = Case::new();
        c.w = Vector3::zeros();
        c.clone.v_gb = Vector3::zeros();
        let j = c.jac();
        assert!(j.h_cam.column(11).norm() < 1e-12 && j.h_cam.column(12).norm() < 1e-12);
    }
}
