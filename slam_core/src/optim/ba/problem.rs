//! The data of a bundle-adjustment problem: keyframes (pose, camera, fixed flag), map points
//! and their observations, plus the per-observation reprojection model and its analytic
//! Jacobians.

use nalgebra::{Isometry3, Matrix2x3, Matrix2x6, Point3, Vector2, Vector3};

use crate::camera::{pose_jacobian, PinholeRadtan};
use crate::CoreError;

/// A keyframe of a bundle-adjustment problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaKeyframe {
    /// World-to-camera pose `T_cw` (`p_c = T_cw p_w`).
    pub t_cw: Isometry3<f64>,
    /// The keyframe's camera (projection with distortion).
    pub camera: PinholeRadtan,
    /// Held constant by the solver (gauge keyframe, or a covisible keyframe outside the
    /// local window in ORB-SLAM's local BA).
    pub fixed: bool,
}

/// A map point of a bundle-adjustment problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaPoint {
    /// Position in the world frame.
    pub p_w: Vector3<f64>,
    /// Held constant by the solver.
    pub fixed: bool,
}

/// One observation: keyframe `keyframe` sees point `point` at pixel `pixel`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaObservation {
    /// Index into [`BaProblem::keyframes`].
    pub keyframe: usize,
    /// Index into [`BaProblem::points`].
    pub point: usize,
    /// The observed (distorted) keypoint, pixels.
    pub pixel: Vector2<f64>,
    /// Information `1 / σ²` (pixels⁻²), `σ = scale_factor^octave`; see
    /// [`crate::features::PyramidScale::inv_sigma2`].
    pub inv_sigma2: f64,
}

/// A bundle-adjustment problem. The solver updates `keyframes[i].t_cw` and
/// `points[j].p_w` in place; observations are never reordered.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BaProblem {
    /// Keyframes (free and fixed).
    pub keyframes: Vec<BaKeyframe>,
    /// Map points (free and fixed).
    pub points: Vec<BaPoint>,
    /// Observations; the solver's inlier flags are indexed like this vector.
    pub observations: Vec<BaObservation>,
}

impl BaProblem {
    /// An empty problem.
    pub fn new() -> Self {
        Self::default()
    }

    /// Empties the problem but keeps its memory, so a mapping thread can refill it.
    pub fn clear(&mut self) {
        self.keyframes.clear();
        self.points.clear();
        self.observations.clear();
    }

    /// Appends a keyframe and returns its index.
    pub fn add_keyframe(
        &mut self,
        t_cw: Isometry3<f64>,
        camera: PinholeRadtan,
        fixed: bool,
    ) -> usize {
        self.keyframes.push(BaKeyframe {
            t_cw,
            camera,
            fixed,
        });
        self.keyframes.len() - 1
    }

    /// Appends a point and returns its index.
    pub fn add_point(&mut self, p_w: Vector3<f64>, fixed: bool) -> usize {
        self.points.push(BaPoint { p_w, fixed });
        self.points.len() - 1
    }

    /// Appends an observation with information `inv_sigma2` and returns its index.
    pub fn add_observation(
        &mut self,
        keyframe: usize,
        point: usize,
        pixel: Vector2<f64>,
        inv_sigma2: f64,
    ) -> usize {
        self.observations.push(BaObservation {
            keyframe,
            point,
            pixel,
            inv_sigma2,
        });
        self.observations.len() - 1
    }

    /// Checks indices and values: every observation refers to an existing keyframe and point,
    /// every pose, point, pixel and camera parameter is finite and every information is
    /// positive and finite. Errors with `InvalidArgument` naming the first offender.
    pub fn validate(&self) -> Result<(), CoreError> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        for (i, k) in self.keyframes.iter().enumerate() {
            let c = &k.camera;
            let cam_ok = finite(&[c.fx, c.fy, c.cx, c.cy, c.k1, c.k2, c.k3, c.p1, c.p2])
                && c.fx != 0.0
                && c.fy != 0.0;
            if !finite(k.t_cw.translation.vector.as_slice())
                || !finite(k.t_cw.rotation.coords.as_slice())
                || !cam_ok
            {
                return Err(CoreError::InvalidArgument(format!(
                    "ba: keyframe {i} has a non-finite pose or an invalid camera"
                )));
            }
        }
        if let Some(j) = self.points.iter().position(|p| !finite(p.p_w.as_slice())) {
            return Err(CoreError::InvalidArgument(format!(
                "ba: point {j} is not finite"
            )));
        }
        for (i, o) in self.observations.iter().enumerate() {
            if o.keyframe >= self.keyframes.len() || o.point >= self.points.len() {
                return Err(CoreError::InvalidArgument(format!(
                    "ba: observation {i} refers to keyframe {} / point {} ({} keyframes, {} points)",
                    o.keyframe,
                    o.point,
                    self.keyframes.len(),
                    self.points.len()
                )));
            }
            if !(finite(o.pixel.as_slice()) && o.inv_sigma2 > 0.0 && o.inv_sigma2.is_finite()) {
                return Err(CoreError::InvalidArgument(format!(
                    "ba: observation {i} has a non-finite pixel or a non-positive information"
                )));
            }
        }
        Ok(())
    }

    /// Residual `π(T_cw p_w) - pixel` of observation `i` in pixels, `None` when the index is
    /// out of range or the point is not in front of the camera.
    pub fn residual(&self, i: usize) -> Option<Vector2<f64>> {
        let o = self.observations.get(i)?;
        let k = self.keyframes.get(o.keyframe)?;
        let p = self.points.get(o.point)?;
        reprojection_residual(&k.camera, &k.t_cw, &p.p_w, &o.pixel)
    }

    /// Root mean square reprojection error (pixels, unweighted) over the observations whose
    /// `mask` entry is true (all when `mask` is `None`) and that project in front of their
    /// camera. `None` when no observation qualifies or the mask has the wrong length.
    pub fn reprojection_rmse(&self, mask: Option<&[bool]>) -> Option<f64> {
        if mask.is_some_and(|m| m.len() != self.observations.len()) {
            return None;
        }
        let (mut sum, mut n) = (0.0, 0usize);
        for i in 0..self.observations.len() {
            if mask.is_some_and(|m| !m[i]) {
                continue;
            }
            if let Some(r) = self.residual(i) {
                sum += r.norm_squared();
                n += 1;
            }
        }
        (n > 0).then(|| (sum / n as f64).sqrt())
    }
}

/// Residual `π(T_cw p_w) - pixel` (pixels), `None` when the point is not in front of the
/// camera (`z <= 1e-9`).
#[inline]
pub fn reprojection_residual(
    camera: &PinholeRadtan,
    t_cw: &Isometry3<f64>,
    p_w: &Vector3<f64>,
    pixel: &Vector2<f64>,
) -> Option<Vector2<f64>> {
    let p_c = (t_cw * Point3::from(*p_w)).coords;
    camera.project(&p_c).map(|uv| uv - pixel)
}

/// The residual of one observation with its analytic Jacobians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReprojectionLinearization {
    /// Residual `π(T_cw p_w) - pixel`, pixels.
    pub residual: Vector2<f64>,
    /// `∂r/∂δ` for the left pose increment `T_cw ← Exp(δ) T_cw`, `δ = [ω; v]`.
    pub d_pose: Matrix2x6<f64>,
    /// `∂r/∂p_w` for the point increment `p_w ← p_w + δp`.
    pub d_point: Matrix2x3<f64>,
}

/// Residual and analytic Jacobians of one observation, through the distortion
/// ([`PinholeRadtan::project_with_jacobian`]): `∂p_c/∂δ = [-[p_c]x | I]` ([`pose_jacobian`]),
/// `∂p_c/∂p_w = R_cw`. `None` when the point is not in front of the camera.
#[inline]
pub fn linearize_reprojection(
    camera: &PinholeRadtan,
    t_cw: &Isometry3<f64>,
    p_w: &Vector3<f64>,
    pixel: &Vector2<f64>,
) -> Option<ReprojectionLinearization> {
    let r_cw = t_cw.rotation.to_rotation_matrix();
    let p_c = r_cw * p_w + t_cw.translation.vector;
    let (uv, du_dp) = camera.project_with_jacobian(&p_c)?;
    Some(ReprojectionLinearization {
        residual: uv - pixel,
        d_pose: pose_jacobian(&du_dp, &p_c),
        d_point: du_dp * r_cw.matrix(),
    })
}
