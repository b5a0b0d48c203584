//! One frame for all VO sessions of a client (issue 15, part 2).
//!
//! A client's tracker starts a new VO session after a tracking failure or a restart; each
//! session has its own map frame and scale (monocular, seed §3.3). Once the server has
//! merged the sessions' maps (seed §3.5), each session's keyframes have a pose in the one
//! server map, so the similarity from a session's map to the server map is the Umeyama
//! Sim(3) of its keyframes' positions, client pose vs final server pose (the server poses
//! are loop-corrected and merged; the merge record alone would miss later corrections).
//! With it, the per-frame poses of every session are expressed
//! - in one session's frame (the per-frame trajectory stays in one frame across
//!   restarts): `S_ref⁻¹ ∘ S_s`, and
//! - in the server map, each frame relative to the nearest keyframe of its session with a
//!   server pose (the keyframe's final pose, the session's scale on the relative motion),
//!   so loop corrections reach every frame.
use std::collections::BTreeMap;

use nalgebra::{Isometry3, Translation3, Vector3};

use crate::geometry::{umeyama, Similarity};

/// Fewest keyframes of a session, with client and server poses, for its Sim(3).
pub const MIN_KEYFRAMES: usize = 3;

/// A pose of a frame (or keyframe) at `t_ns`: camera to map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedPose {
    /// Frame time, ns.
    pub t_ns: i64,
    /// Camera-to-map pose `T_wc`.
    pub t_wc: Isometry3<f64>,
}

/// A per-frame pose with its VO session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionPose {
    /// VO session of the frame's pose.
    pub session: u32,
    /// The pose in that session's map.
    pub pose: TimedPose,
}

/// A session's map in the server map.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionLink {
    /// Session map → server map.
    pub to_server: Similarity,
    /// The session's keyframes with both poses (client, server), by time.
    pub keyframes: Vec<(TimedPose, TimedPose)>,
    /// RMS distance of the keyframes' aligned client positions to their server positions,
    /// server-map units.
    pub rmse: f64,
}

/// Why a session could not be tied to the server map.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NoLink {
    /// Fewer than [`MIN_KEYFRAMES`] of its keyframes are in the server map.
    TooFewKeyframes(usize),
    /// Umeyama failed (collapsed keyframe positions).
    Degenerate(String),
}

/// The session of the frame at `t_ns` (frames sorted by time), if one has that time.
fn session_at(frames: &[SessionPose], t_ns: i64) -> Option<u32> {
    let i = frames.binary_search_by_key(&t_ns, |f| f.pose.t_ns).ok()?;
    Some(frames[i].session)
}

/// Each session's link to the server map. `frames` sorted by time (each keyframe's
/// session is that of the frame at its time); `client_kfs` as the tracker sent them (the
/// session's map), `server_kfs` in the final server map.
pub fn session_links(
    frames: &[SessionPose],
    client_kfs: &[TimedPose],
    server_kfs: &[TimedPose],
) -> BTreeMap<u32, Result<SessionLink, NoLink>> {
    let server: BTreeMap<i64, &TimedPose> = server_kfs.iter().map(|k| (k.t_ns, k)).collect();
    let mut pairs: BTreeMap<u32, Vec<(TimedPose, TimedPose)>> = BTreeMap::new();
    for f in frames {
        pairs.entry(f.session).or_default();
    }
    for k in client_kfs {
        if let (Some(s), Some(srv)) = (session_at(frames, k.t_ns), server.get(&k.t_ns)) {
            pairs.entry(s).or_default().push((*k, **srv));
        }
    }
    pairs
        .into_iter()
        .map(|(s, kfs)| (s, link_of(kfs)))
        .collect()
}

fn link_of(mut keyframes: Vec<(TimedPose, TimedPose)>) -> Result<SessionLink, NoLink> {
    keyframes.sort_by_key(|(c, _)| c.t_ns);
    if keyframes.len() < MIN_KEYFRAMES {
        return Err(NoLink::TooFewKeyframes(keyframes.len()));
    }
    let pos = |p: &TimedPose| p.t_wc.translation.vector;
    let src: Vec<Vector3<f64>> = keyframes.iter().map(|(c, _)| pos(c)).collect();
    let dst: Vec<Vector3<f64>> = keyframes.iter().map(|(_, s)| pos(s)).collect();
    let to_server = umeyama(&src, &dst, true).map_err(|e| NoLink::Degenerate(e.to_string()))?;
    let sq: f64 = src
        .iter()
        .zip(&dst)
        .map(|(a, b)| (to_server.transform_point(a) - b).norm_squared())
        .sum();
    Ok(SessionLink {
        to_server,
        rmse: (sq / src.len() as f64).sqrt(),
        keyframes,
    })
}

/// The per-frame poses in the map of session `reference`: a frame of another session
/// through `S_ref⁻¹ ∘ S_s`; `None` for a frame whose session (or the reference) has no
/// link.
pub fn in_session_frame(
    frames: &[SessionPose],
    links: &BTreeMap<u32, Result<SessionLink, NoLink>>,
    reference: u32,
) -> Vec<Option<TimedPose>> {
    let to_ref = |s: u32| -> Option<Similarity> {
        if s == reference {
            return Some(Similarity::identity());
        }
        let r = links.get(&reference)?.as_ref().ok()?;
        let l = links.get(&s)?.as_ref().ok()?;
        Some(r.to_server.inverse().compose(&l.to_server))
    };
    frames
        .iter()
        .map(|f| {
            to_ref(f.session).map(|sim| TimedPose {
                t_ns: f.pose.t_ns,
                t_wc: sim.transform_pose(&f.pose.t_wc),
            })
        })
        .collect()
}

/// The per-frame poses in the server map, each relative to the nearest (in time) keyframe
/// of its session with a server pose: `T_srv(f) = T_srv(k) · scaled(T_cli(k)⁻¹ T_cli(f))`,
/// the relative translation scaled by the session's Sim(3) scale. `None` for a frame whose
/// session has no link.
pub fn in_server_map(
    frames: &[SessionPose],
    links: &BTreeMap<u32, Result<SessionLink, NoLink>>,
) -> Vec<Option<TimedPose>> {
    frames
        .iter()
        .map(|f| {
            let link = links.get(&f.session)?.as_ref().ok()?;
            let kfs = &link.keyframes;
            let i = kfs.partition_point(|(c, _)| c.t_ns < f.pose.t_ns);
            let near = [i.checked_sub(1), (i < kfs.len()).then_some(i)]
                .into_iter()
                .flatten()
                .min_by_key(|&j| (kfs[j].0.t_ns - f.pose.t_ns).abs())?;
            let (cli, srv) = &kfs[near];
            let rel = cli.t_wc.inverse() * f.pose.t_wc;
            let rel = Isometry3::from_parts(
                Translation3::from(rel.translation.vector * link.to_server.scale),
                rel.rotation,
            );
            Some(TimedPose {
                t_ns: f.pose.t_ns,
                t_wc: srv.t_wc * rel,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    /// Ground truth on a circle (server map), 10 frames per second.
    fn gt(k: usize) -> TimedPose {
        let a = k as f64 * 0.05;
        let p = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.2 * a.sin());
        let q = UnitQuaternion::from_euler_angles(0.1, -0.2, a + 1.0);
        TimedPose {
            t_ns: k as i64 * 100_000_000,
            t_wc: Isometry3::from_parts(Translation3::from(p), q),
        }
    }

    fn sim(yaw: f64, t: [f64; 3], scale: f64) -> Similarity {
        Similarity {
            rotation: Rotation3::from_euler_angles(0.0, 0.3, yaw),
            translation: Vector3::from(t),
            scale,
        }
    }

    /// Two sessions (frames 0-59, 60-119), each in its own map `A_s⁻¹(server)`, keyframes
    /// every 5 frames, all in the server map.
    fn two_sessions() -> (
        Vec<SessionPose>,
        Vec<TimedPose>,
        Vec<TimedPose>,
        [Similarity; 2],
    ) {
        let a = [
            sim(0.4, [1.0, -2.0, 0.5], 0.25),
            sim(-1.2, [0.3, 4.0, -1.0], 3.5),
        ];
        let frames: Vec<SessionPose> = (0..120)
            .map(|k| {
                let s = (k >= 60) as u32;
                let g = gt(k);
                SessionPose {
                    session: s + 7,
                    pose: TimedPose {
                        t_ns: g.t_ns,
                        t_wc: a[s as usize].inverse().transform_pose(&g.t_wc),
                    },
                }
            })
            .collect();
        let client: Vec<TimedPose> = frames.iter().step_by(5).map(|f| f.pose).collect();
        let server: Vec<TimedPose> = (0..120).step_by(5).map(gt).collect();
        (frames, client, server, a)
    }

    fn close(a: &Isometry3<f64>, b: &Isometry3<f64>) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9
            && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    #[test]
    fn every_session_in_the_first_sessions_frame() {
        let (frames, client, server, a) = two_sessions();
        let links = session_links(&frames, &client, &server);
        assert_eq!(links.len(), 2);
        for (s, l) in &links {
            let l = l.as_ref().unwrap();
            assert_eq!(l.keyframes.len(), 12, "session {s}");
            assert!(l.rmse < 1e-9);
        }
        let out = in_session_frame(&frames, &links, 7);
        for (k, o) in out.iter().enumerate() {
            let want = a[0].inverse().transform_pose(&gt(k).t_wc);
            assert!(close(&o.unwrap().t_wc, &want), "frame {k}");
        }
    }

    #[test]
    fn every_frame_in_the_server_map() {
        let (frames, client, server, _) = two_sessions();
        let links = session_links(&frames, &client, &server);
        for (k, o) in in_server_map(&frames, &links).iter().enumerate() {
            assert!(close(&o.unwrap().t_wc, &gt(k).t_wc), "frame {k}");
        }
    }

    #[test]
    fn a_session_without_server_keyframes_is_not_expressed() {
        let (frames, client, server, _) = two_sessions();
        // Only 2 keyframes of the second session reached the server map.
        let server: Vec<TimedPose> = server
            .into_iter()
            .filter(|k| k.t_ns < 6_700_000_000)
            .collect();
        let links = session_links(&frames, &client, &server);
        assert_eq!(links[&8], Err(NoLink::TooFewKeyframes(2)));
        let out = in_session_frame(&frames, &links, 7);
        assert!(out[..60].iter().all(Option::is_some));
        assert!(out[60..].iter().all(Option::is_none));
    }
}
