//! Replays a mapper journal through a fresh keyframe handler and prints one line per
//! keyframe (status, inliers, measured and smoothed scale ratio, prediction error): a
//! diagnosis tool for the server keyframe handler (seed §3.4.1).
//!
//! `cargo run --release --example journal_trace -- OUT/mapper_journal.bin`
use std::collections::BTreeMap;

use shoal_runtime::journal::{read_journal, Entry};
use slam_core::server::{HandlerParams, KeyframeHandler, ServerMaps};

fn main() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: journal_trace JOURNAL"))?;
    let scale: f64 = std::env::args()
        .nth(2)
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    let out = std::env::args().nth(3);
    let contents = read_journal(std::path::Path::new(&path))?;
    let mut handlers: BTreeMap<u32, KeyframeHandler> = BTreeMap::new();
    let mut maps = ServerMaps::new();
    println!(
        "t_s id inertial status inliers new lambda_meas lambda pred_err_m pred_err_deg |t_ck|"
    );
    for e in contents.entries {
        let Entry::Keyframe {
            client,
            header,
            records,
        } = e
        else {
            continue;
        };
        let mut kf = mapper::convert::server_keyframe(client, &header, &records)
            .map_err(anyhow::Error::msg)?;
        kf.t_ck.translation.vector *= scale;
        let t_ck_norm = kf.t_ck.translation.vector.norm();
        let h = handlers
            .entry(client)
            .or_insert_with(|| KeyframeHandler::new(client, HandlerParams::default()));
        let r = h.handle(&mut maps, kf)?;
        let (pe, pa) = match (r.t_sk, r.t_sk_predicted) {
            (Some(a), Some(b)) => (
                (a.translation.vector - b.translation.vector).norm(),
                a.rotation.angle_to(&b.rotation).to_degrees(),
            ),
            _ => (f64::NAN, f64::NAN),
        };
        println!(
            "{:.2} {} {} {:?} {} {} {:?} {:.4} {:.4} {:.2} {:.3}",
            header.t_ns as f64 * 1e-9,
            header.keyframe_id,
            header.inertial,
            r.status,
            r.inliers,
            r.new_points,
            r.lambda_measured.map(|l| (l * 1e4).round() / 1e4),
            r.lambda,
            pe,
            pa,
            t_ck_norm
        );
        let np: usize = maps.values().map(|m| m.map.points.len()).sum();
        if let Some(ir) = h.idle_step(&mut maps) {
            let np2: usize = maps.values().map(|m| m.map.points.len()).sum();
            eprintln!(
                "  points {np} -> {np2}, culled {:?}, ba {:?}",
                ir.culled,
                ir.ba.map(|b| (
                    b.initial_rmse,
                    b.final_rmse,
                    b.iterations,
                    b.rejected_steps,
                    b.n_outliers,
                    b.aborted
                ))
            );
        }
    }
    if let Some(out) = out {
        let mut text = String::new();
        for m in maps.values() {
            for (t, p) in m.trajectory() {
                let (q, v) = (p.rotation.coords, p.translation.vector);
                text += &format!(
                    "{:.9} {} {} {} {} {} {} {}\n",
                    t as f64 * 1e-9,
                    v.x,
                    v.y,
                    v.z,
                    q.x,
                    q.y,
                    q.z,
                    q.w
                );
            }
        }
        std::fs::write(out, text)?;
    }
    Ok(())
}
