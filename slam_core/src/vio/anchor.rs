//! Anchoring a visual-inertial client's world to its server map (issue 19: the feedback to a
//! visual-inertial client is metric and gravity-aligned, and the client applies it without
//! a jump in its local window).
//!
//! A metric, gravity-aligned client session and the metric, gravity-aligned server map its
//! keyframes are in differ by a rigid motion with 4 degrees of freedom (`VI_NOTES.md` §4
//! "Server"): a turn about gravity and a translation, which hold the client's drift and,
//! after a merge, the frame of the map it joined. The server's feedback on keyframe `j` (its
//! server pose `T_sj`, seed §3.4.1) and the pose the client sent for it (`T_cj`, in the
//! session's own world) give it: `A = T_sj T_cj⁻¹`, reduced to yaw and translation
//! ([`anchor_4dof`]; roll and pitch stay the client's own gravity estimate, and the
//! translation puts keyframe `j`'s camera centre where the server has it).
//!
//! The client moves its whole session by the change `Δ = A A_now⁻¹` before its next frame
//! ([`super::VioTracker::request_anchor`]): VO map, tracking state, coupler, orientation
//! and navigator together. `Δ` is rigid and keeps gravity on `z`, so the local window's
//! relative poses, IMU factors and biases are untouched and its velocities turn with it:
//! tracking goes on from the moved state as it would have from the old one. Only the
//! frame its poses are given in changes: from then on a frame's pose as tracked and its
//! server-map pose agree up to the drift since the last feedback. Like an initialisation,
//! the move re-expresses the session's earlier poses for the recorder (`FLAG_WORLD_MOVE`),
//! so the recorded trajectory stays the client's own estimate, in its latest frame.
//!
//! The keyframes it sends stay in the session's own world (seed §3.4.1: the server's
//! predictions, eq. 3.1 and 3.4, difference the client poses of consecutive keyframes, and
//! the client "should not transform its poses" under them): the tracker keeps `A_now` per
//! session ([`SessionAnchor`]) and sends `A_now⁻¹ T_ck`, and the session's other world moves
//! (a refinement's `M`) conjugate it, `A ← M A M⁻¹`, so that the session world moves by `M`
//! exactly as it did before anchors existed.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use crate::ids::MapId;
use crate::lie::Sim3;

/// When a client re-anchors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorParams {
    /// Re-anchor at all (`false`: poses stay in the session's world, the server-map pose of
    /// each frame comes from eq. 3.1 and 3.4 alone, as for a monocular client).
    pub enabled: bool,
    /// A change of the anchor below both thresholds is not applied (each move waits for
    /// local mapping to be idle), m.
    pub min_translation_m: f64,
    /// Its yaw threshold, degrees.
    pub min_yaw_deg: f64,
}

impl Default for AnchorParams {
    /// 1 cm or 0.1°.
    fn default() -> Self {
        Self {
            enabled: true,
            min_translation_m: 0.01,
            min_yaw_deg: 0.1,
        }
    }
}

/// The yaw `ψ` of a rotation about the world's `z` (gravity) axis, from the rotation's
/// upper-left 2x2 block: `atan2(R₁₀ - R₀₁, R₀₀ + R₁₁)` (exact for `R_z(ψ)`, the closest yaw
/// for a rotation tilted away from `z`).
pub fn yaw_of(r: &UnitQuaternion<f64>) -> f64 {
    let m = r.to_rotation_matrix();
    let m = m.matrix();
    (m[(1, 0)] - m[(0, 1)]).atan2(m[(0, 0)] + m[(1, 1)])
}

/// The 4-DoF anchor `A` (session world → server map) from one keyframe seen by both: its
/// camera-to-world pose `t_wc` in the session's world and `t_sc` in the server map. The
/// rotation is the yaw of `R_sc R_wcᵀ`; the translation maps the camera centre exactly.
pub fn anchor_4dof(t_wc: &Isometry3<f64>, t_sc: &Isometry3<f64>) -> Isometry3<f64> {
    let yaw = yaw_of(&(t_sc.rotation * t_wc.rotation.inverse()));
    let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    let t = t_sc.translation.vector - r * t_wc.translation.vector;
    Isometry3::from_parts(Translation3::from(t), r)
}

/// Whether an anchor change is worth a world move ([`AnchorParams`]).
pub fn is_significant(delta: &Isometry3<f64>, p: &AnchorParams) -> bool {
    delta.translation.vector.norm() >= p.min_translation_m
        || yaw_of(&delta.rotation).abs().to_degrees() >= p.min_yaw_deg
}

/// A session's anchor as the tracker keeps it: the session's world → the client's present
/// world (module docs), and the server map it was last anchored to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionAnchor {
    /// The session (wire id).
    pub session: u32,
    /// `A_now`: a point `x` of the session's world is at `A x` in the client's world.
    pub a: Isometry3<f64>,
    /// The server map of the last anchor (or of the session's first metric feedback).
    pub map_id: MapId,
}

/// What the client is asked to do with its world ([`SessionAnchor::request`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorRequest {
    /// The session (wire id).
    pub session: u32,
    /// `Δ`, the client world's move.
    pub delta: Isometry3<f64>,
    /// The server map anchored to.
    pub map_id: MapId,
    /// The anchor changes the map (a merge moved the client's map into another's frame);
    /// within one map, the move corrects the client's drift (or follows a correction of
    /// the map). Always applied when the map changes, whatever its size.
    pub new_map: bool,
}

impl SessionAnchor {
    /// A session not moved yet, in server map `map_id`.
    pub fn new(session: u32, map_id: MapId) -> Self {
        Self {
            session,
            a: Isometry3::identity(),
            map_id,
        }
    }

    /// The move that anchors the session to server map `map_id`, where keyframe `j`
    /// (`t_wc_j` as sent, in the session's world) is at `t_sc_j`; `None` when below the
    /// thresholds.
    pub fn request(
        &self,
        t_wc_j: &Isometry3<f64>,
        t_sc_j: &Isometry3<f64>,
        map_id: MapId,
        p: &AnchorParams,
    ) -> Option<AnchorRequest> {
        let target = anchor_4dof(t_wc_j, t_sc_j);
        let delta = target * self.a.inverse();
        let new_map = map_id != self.map_id;
        (new_map || is_significant(&delta, p)).then_some(AnchorRequest {
            session: self.session,
            delta,
            map_id,
            new_map,
        })
    }

    /// The client applied `r`.
    pub fn applied(&mut self, r: &AnchorRequest) {
        self.a = r.delta * self.a;
        self.map_id = r.map_id;
    }

    /// The session's world moved by `m` for another reason (an initialisation's
    /// refinement, a gravity correction): the session world moves with it, `A ← M A M⁻¹`.
    pub fn on_world_move(&mut self, m: &Sim3) {
        let a = Sim3::from_isometry(&self.a, 1.0);
        self.a = m.compose(&a).compose(&m.inverse()).to_isometry();
    }

    /// The rigid move from the client's present world back to the session's, `A⁻¹`.
    pub fn to_session(&self) -> Isometry3<f64> {
        self.a.inverse()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot(x: f64, y: f64, z: f64) -> UnitQuaternion<f64> {
        UnitQuaternion::from_scaled_axis(Vector3::new(x, y, z))
    }

    /// A server map that differs from the session by yaw and translation gives that anchor
    /// back from any keyframe; a small tilt of the server's gravity is not taken.
    #[test]
    fn the_anchor_is_the_yaw_and_translation_between_the_frames() {
        let truth = Isometry3::from_parts(
            Translation3::new(4.0, -2.5, 0.75),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2.4),
        );
        let t_wc = Isometry3::from_parts(Translation3::new(1.0, 2.0, 1.5), rot(1.2, -0.3, 0.8));
        let a = anchor_4dof(&t_wc, &(truth * t_wc));
        assert!((a.translation.vector - truth.translation.vector).norm() < 1e-12);
        assert!(a.rotation.angle_to(&truth.rotation) < 1e-12);
        let tilt = Isometry3::from_parts(Translation3::identity(), rot(0.01, -0.02, 0.0));
        let t_sc = tilt * truth * t_wc;
        let a = anchor_4dof(&t_wc, &t_sc);
        assert!(
            (yaw_of(&a.rotation) - 2.4).abs() < 1e-3,
            "{}",
            yaw_of(&a.rotation)
        );
        let centre = a * nalgebra::Point3::from(t_wc.translation.vector);
        assert!((centre.coords - t_sc.translation.vector).norm() < 1e-12);
    }

    /// Requests compose to the anchor asked for; a refinement's move conjugates the anchor
    /// so that un-anchoring gives the session world moved by the refinement.
    #[test]
    fn requests_compose_and_world_moves_conjugate() {
        let map = MapId::from_raw(3);
        let mut s = SessionAnchor::new(7, map);
        let p = AnchorParams::default();
        let t_wc = Isometry3::from_parts(Translation3::new(1.0, 2.0, 1.5), rot(0.2, 0.1, 0.3));
        let target = Isometry3::from_parts(
            Translation3::new(0.5, 0.0, -0.2),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3),
        );
        let r = s.request(&t_wc, &(target * t_wc), map, &p).expect("a move");
        assert!(!r.new_map);
        s.applied(&r);
        assert!((s.a.translation.vector - target.translation.vector).norm() < 1e-12);
        assert!(
            s.request(&t_wc, &(target * t_wc), map, &p).is_none(),
            "anchored"
        );
        let other = s.request(&t_wc, &(target * t_wc), MapId::from_raw(4), &p);
        assert!(
            other.is_some_and(|o| o.new_map),
            "a new map is always applied"
        );
        // A refinement M of the present world: x_present' = M x_present; the session world
        // moves by M too, so A' x_session' = M A x_session for x_session' = M x_session.
        let m = Sim3::new(rot(0.0, 0.01, 0.02), Vector3::new(0.1, 0.2, 0.0), 1.03);
        let x = Vector3::new(3.0, -1.0, 2.0);
        let before = m.transform_point(&(s.a * nalgebra::Point3::from(x)).coords);
        s.on_world_move(&m);
        let after = s.a * nalgebra::Point3::from(m.transform_point(&x));
        assert!((before - after.coords).norm() < 1e-12);
    }
}
