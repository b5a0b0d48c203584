//! Localising in a saved map before the client's own VO initialises (issue 20;
//! `tracker.prior_map`, which `shoal run --load-map` sets for monocular clients).
//!
//! The ports read the file and give the core the map's client form
//! ([`TrackerCore::set_prior_map`], [`slam_core::vo::prior`]). With the first frame the
//! core makes a second VO started in that map ([`slam_core::vo::VoTracker::
//! start_in_prior_map`]). Until the client's own VO has initialised, every frame goes to
//! both, the prior's first: the first frame the prior VO poses, it becomes the client
//! (the other VO, with its initialisation attempts, is dropped) and the session continues
//! in the saved map's world and scale. When the own VO initialises first, the prior is
//! dropped, and the server's loop closer finds the loaded map later, as without a prior.
//!
//! The prior keyframes stay in the VO's window until they leave it like any other, but
//! they are never sent, spooled or counted as the client's ([`is_prior_keyframe`]).
use slam_core::vo::{is_prior_keyframe, ClientMap, Keyframe, VoFrame, VoState};

use super::{Client, ClientOutput, TrackerCore};

/// The saved map, until the first frame; then the VO started in it, until one of the
/// two VOs poses a frame.
pub(super) enum Prior {
    /// The map, waiting for the camera of the first frame.
    Map(Box<ClientMap>),
    /// The VO trying to relocalise in it.
    Trying(Box<Client>),
}

impl TrackerCore {
    /// Gives the core saved map `map` (prior keyframes, [`slam_core::vo::prior_client_map`])
    /// to localise in before the monocular VO initialises (module docs). Ignored outside
    /// the monocular mode.
    pub fn set_prior_map(&mut self, map: ClientMap) {
        if self.cfg.mode == crate::ClientMode::Vio || self.cfg.mode == crate::ClientMode::Calib {
            return;
        }
        self.counters.prior_map_keyframes = map.keyframes.len() as u64;
        self.counters.prior_map_points = map.points.len() as u64;
        self.prior = Some(Prior::Map(Box::new(map)));
    }

    /// The VO started in the prior map, for frames like `h` (the first).
    pub(super) fn start_prior(&mut self, h: &shm_schema::FrameHeader) {
        let Some(Prior::Map(map)) = self.prior.take() else {
            return;
        };
        let started = self.new_vo(h).and_then(|mut vo| {
            vo.start_in_prior_map(*map)?;
            Ok(vo)
        });
        match started {
            Ok(vo) => self.prior = Some(Prior::Trying(Box::new(Client::Mono(Box::new(vo))))),
            Err(e) => {
                let detail = format!("client {}: prior map not used: {e}", self.cfg.client);
                self.status.error(shoal_runtime::ErrorKind::MapFile, detail);
            }
        }
    }

    /// The frame through the prior VO while the client's VO initialises: its output when
    /// it posed the frame (it is the client from now on), else `None` (the client's VO
    /// takes the frame). Drops the prior once the client's VO has initialised.
    pub(super) fn prior_step(
        &mut self,
        frame: &VoFrame<'_>,
    ) -> Result<Option<ClientOutput>, slam_core::CoreError> {
        let own_initialising = self.client.as_ref().is_some_and(|c| {
            matches!(
                c.vo().state(),
                VoState::NotInitialized | VoState::Initializing
            )
        });
        let Some(Prior::Trying(p)) = self.prior.as_mut() else {
            return Ok(None);
        };
        if !own_initialising {
            self.prior = None;
            return Ok(None);
        }
        self.counters.prior_map_frames_tried += 1;
        let o = p.process(frame)?;
        if o.t_cw.is_none() || p.vo().awaiting_prior() {
            return Ok(None);
        }
        let Some(Prior::Trying(p)) = self.prior.take() else {
            return Ok(None);
        };
        self.client = Some(*p);
        self.counters.prior_map_relocalised = 1;
        self.counters.prior_map_relocalised_t_ns = frame.t_ns.max(0) as u64;
        Ok(Some(o))
    }
}

/// Drops the prior keyframes of `kfs` (never the client's to send); returns how many.
pub(super) fn drop_prior_keyframes(kfs: &mut Vec<Keyframe>) -> u64 {
    let n = kfs.len();
    kfs.retain(|k| !is_prior_keyframe(k.id));
    (n - kfs.len()) as u64
}
