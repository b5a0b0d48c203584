//! Measures the synthetic renderer's speed (one thread) and optionally saves a few frames.
//!
//! `cargo run --release -p datasets --example sim_render_fps -- [scenario] [frames] [png_dir]`
use std::time::Instant;

use datasets::sim::{Scenario, SimParams, SimWorld};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let scenario: Scenario = args.get(1).map_or(Ok(Scenario::FastRs), |s| s.parse())?;
    let frames: usize = args.get(2).map_or(Ok(200), |s| s.parse())?;
    let png_dir = args.get(3);
    let t = Instant::now();
    let world = SimWorld::new(SimParams::new(scenario))?;
    println!("scene + IMU built in {:.2} s", t.elapsed().as_secs_f64());
    let cam = *world.camera();
    let mut img = vec![0u8; cam.width as usize * cam.height as usize];
    let n = frames.min(world.n_frames());
    let cpu0 = thread_cpu_s();
    let t = Instant::now();
    let mut checksum = 0u64;
    for k in 0..n {
        world.render_frame_into(k, &mut img)?;
        checksum = checksum.wrapping_add(u64::from(img[k % img.len()]));
        if let Some(dir) = png_dir {
            if k % 50 == 0 {
                let path = std::path::Path::new(dir).join(format!("{scenario}_{k:05}.png"));
                image::save_buffer(
                    &path,
                    &img,
                    cam.width,
                    cam.height,
                    image::ExtendedColorType::L8,
                )?;
            }
        }
    }
    let s = t.elapsed().as_secs_f64();
    let cpu = thread_cpu_s().zip(cpu0).map(|(a, b)| a - b);
    if let Some(cpu) = cpu {
        println!(
            "CPU time of the rendering thread: {cpu:.2} s -> {:.1} fps on one core ({:.2} ms/frame)",
            n as f64 / cpu,
            1e3 * cpu / n as f64
        );
    }
    println!(
        "{scenario}: {n} frames {}x{} in {s:.2} s -> {:.1} fps ({:.2} ms/frame), readout {} ns [{checksum}]",
        cam.width,
        cam.height,
        n as f64 / s,
        1e3 * s / n as f64,
        world.readout_ns()
    );
    Ok(())
}

/// CPU time (user + system) of the calling thread from `/proc/thread-self/stat` (Linux;
/// 100 Hz ticks assumed), `None` elsewhere.
fn thread_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // After the command name: state is field 3 of the full line, utime 14 and stime 15.
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}
