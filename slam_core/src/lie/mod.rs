//! The one copy of the Lie-group math: SO(3), SE(3) and Sim(3) exponentials, logarithms,
//! adjoints, hat/vee, and right and left Jacobians with their inverses. Everything else in
//! the workspace (tracking, bundle adjustment, pose-graph optimisation, loop closing, the
//! visual-inertial factors to come) calls these functions.
//!
//! **Tangent order: rotation first**, as GTSAM and `VI_NOTES.md` write it:
//! - SO(3): `ω ∈ ℝ³`, a rotation vector (angle `|ω|`, [`so3`]);
//! - SE(3): `ξ = [ω; v]`, `Exp(ξ) = [Exp(ω), Jl(ω) v]` ([`se3`]);
//! - Sim(3): `ξ = [ω; ρ; σ]` (rotation, translation, log-scale),
//!   `Exp(ξ) = [e^σ Exp(ω), W(ω, σ) ρ]` ([`sim3`]). The seed's minimal vector `(ν, ω, σ)`
//!   (§2.2, eq. 2.23) is the same map with the translation listed first.
//!
//! Information matrices, Jacobian columns and increments everywhere use this order; a
//! function taking a twist from another order (a g2o file's `(t, R)` information, ...)
//! permutes at that boundary.
//!
//! **Frames.** `T_ab` maps coordinates in frame `b` to frame `a`: `x_a = R_ab x_b + t_ab`
//! (Sim(3): `x_a = s R_ab x_b + t_ab`). Compose `T_ac = T_ab T_bc`.
//!
//! **Perturbations.** The group functions are side-neutral; each optimiser states its side:
//! - right (GTSAM, pose graphs, IMU preintegration): `X ← X Exp(δ)`; then
//!   `Log(Exp(ξ) Exp(δ)) ≈ ξ + Jr(ξ)⁻¹ δ` and `Exp(ξ + δ) ≈ Exp(ξ) Exp(Jr(ξ) δ)`;
//! - left (tracking and bundle adjustment on `T_cw`, Sim(3) loop refinement, the error state
//!   `R = Exp(δθ) R̂` of `VI_NOTES.md` §0): `X ← Exp(δ) X`; then
//!   `Log(Exp(δ) Exp(ξ)) ≈ ξ + Jl(ξ)⁻¹ δ`, `Jl(ξ) = Jr(-ξ)`.
//!
//! Moving a perturbation across a pose uses the adjoint: `X Exp(δ) X⁻¹ = Exp(Ad_X δ)`.
//!
//! **Why not a crate.** We checked `apex-solver` (the Lie groups live in its
//! `apex-manifolds` 0.4): it pulls nalgebra 0.33 beside our 0.35 (two copies compiled, and its
//! `Isometry3` is not ours), plus `rand` and `tracing`, and needs Rust 1.93 (our MSRV is
//! 1.89); the full solver adds rayon, chrono, tracing-subscriber, slotmap and its own IO and
//! camera crates. Its SE(3) and Sim(3) tangents are `[ρ; θ]` and `[ρ; θ; σ]` (translation
//! first, the manif convention), the opposite of ours, and it is ~13k lines (SE2, SE23,
//! SGal3, ...) where we need three groups. About 600 lines of tested code here cost less
//! than that build.

pub mod se3;
pub mod sim3;
pub mod so3;

pub use se3::{se3_adjoint, se3_exp, se3_hat, se3_jl, se3_jl_inv, se3_jr, se3_jr_inv, se3_log};
pub use sim3::{sim3_ad, sim3_hat, sim3_jr, sim3_jr_inv, sim3_w, Matrix7, Sim3, Vector7};
pub use so3::{
    quat_exp, quat_log, skew, so3_exp, so3_jl, so3_jl_inv, so3_jr, so3_jr_inv, so3_log, vee,
};
