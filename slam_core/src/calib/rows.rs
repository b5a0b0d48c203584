//! The rows one feature contributes to the update (`VI_NOTES.md` §3 "Measurement in row v
//! of image j" and "Update"): each observation's body state at its row time, the anchored
//! inverse-depth triangulation, the stacked Jacobians `H_x`, `H_f` and their projection on
//! the left null space of `H_f`.

use nalgebra::{DMatrix, DVector, Vector2};

use super::filter::CalibFilter;
use super::integrate::integrate;
use super::measure::{observe, AnchorPose, RowPose};
use super::propagate::rate_jacobians;
use super::state::{clone_offset, CloneState, NavState};
use super::triangulate::{triangulate, CameraPose};
use super::update::{project_null_space, Projected};
use super::{CAM_BLOCK, CLONE_DIM, CORE_DIM, IDX_PCB};

impl CalibFilter {
    /// The row pose of an observation at pixel `uv` in clone `c`: the body state when the
    /// rolling shutter read `uv`'s line ([`crate::camera::PinholeRadtan::readout_fraction`]).
    pub(crate) fn row_pose(&self, c: &CloneState, uv: &Vector2<f64>) -> Option<RowPose> {
        let shutter = self.state.camera.readout_fraction(uv);
        let delta = (self.state.t_d - c.t_d_at_clone) + shutter * self.state.t_r;
        let t0 = c.tau_ns as f64;
        let (nav, omega_b, accel_b) =
            integrate(&self.state, &self.imu, &c.nav, t0, t0 + delta * 1e9)?;
        let p_lin = if self.params.fej {
            c.p_fej + c.v_fej * delta
        } else {
            nav.p_gb
        };
        Some(RowPose {
            nav,
            omega_b,
            accel_b,
            delta,
            shutter,
            p_lin,
        })
    }

    /// Camera pose of a body state: `R_gc = R_gb R_cbᵀ`, `p_gc = p_gb - R_gc p_cb`.
    pub(super) fn camera_pose(&self, nav: &NavState) -> CameraPose {
        let r_gc = nav.r_gb * self.state.r_cb.inverse();
        CameraPose {
            r_gc,
            p_gc: nav.p_gb - r_gc * self.state.p_cb,
        }
    }

    /// One feature's projected rows and whether it was fitted with the depth prior
    /// ([`super::triangulate::Triangulated::low_parallax`]), or `None` when it cannot be used.
    pub(super) fn feature_rows(&self, track: &[(u64, Vector2<f64>)]) -> Option<(Projected, bool)> {
        let first = self.clones.front()?.id;
        let idx: Vec<usize> = track.iter().map(|o| (o.0 - first) as usize).collect();
        let a = *idx.iter().max()?;
        let anchor_c = self.clones.get(a)?;
        let rows: Vec<RowPose> = track
            .iter()
            .zip(&idx)
            .map(|(o, &i)| self.row_pose(self.clones.get(i)?, &o.1))
            .collect::<Option<_>>()?;
        let views: Vec<(CameraPose, Vector2<f64>)> = rows
            .iter()
            .zip(track)
            .map(|(r, o)| (self.camera_pose(&r.nav), o.1))
            .collect();
        let anchor_cam = self.camera_pose(&anchor_c.nav);
        let tri = triangulate(
            &self.state.camera,
            &anchor_cam,
            &views,
            self.params.min_parallax,
            self.params.low_parallax,
        )?;
        if tri.rms > self.params.max_triangulation_rms {
            return None;
        }
        let p_lin = if self.params.fej {
            anchor_c.p_fej
        } else {
            anchor_c.nav.p_gb
        };
        let anchor = AnchorPose {
            nav: anchor_c.nav,
            p_lin,
        };
        let m = 2 * track.len();
        let dim = self.p.nrows();
        let mut h_x = DMatrix::zeros(m, dim);
        let mut h_f = DMatrix::zeros(m, 3);
        let mut r = DVector::zeros(m);
        for (k, ((o, &i), row)) in track.iter().zip(&idx).zip(&rows).enumerate() {
            let j = observe(&self.state, row, &anchor, &tri.f)?;
            let at = 2 * k;
            r.rows_mut(at, 2).copy_from(&(o.1 - j.z));
            h_f.view_mut((at, 0), (2, 3)).copy_from(&j.h_f);
            h_x.view_mut((at, clone_offset(i)), (2, CLONE_DIM))
                .copy_from(&j.h_clone);
            let mut ha = h_x.view_mut((at, clone_offset(a)), (2, 6));
            ha += j.h_anchor;
            h_x.view_mut((at, IDX_PCB), (2, CAM_BLOCK))
                .copy_from(&j.h_cam);
            let (_, jw) = rate_jacobians(&self.state, &row.omega_b, &row.accel_b);
            let mut hc = h_x.view_mut((at, 0), (2, CORE_DIM));
            hc += j.h_omega * jw;
        }
        Some((project_null_space(h_x, h_f, r)?, tri.low_parallax))
    }
}
