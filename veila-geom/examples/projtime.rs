use glam::Vec3;
use std::time::Instant;
use veila_geom::{AngleMethod, LidarSensor, ProjectionOptions, Projector};
fn main() {
    let bytes = std::fs::read("/work/shared/data/real/kitti/training/velodyne/000000.bin").unwrap();
    let pts: Vec<Vec3> = bytes.chunks_exact(16).map(|c| {
        let f = |i: usize| f32::from_le_bytes(c[i * 4..i * 4 + 4].try_into().unwrap());
        Vec3::new(f(0), f(1), f(2))}).collect();
    // calibration loop
    let t = Instant::now(); let mut acc = 0.0f64;
    for _ in 0..20 { for p in &pts { acc += (f64::from(p.x) * f64::from(p.x) + f64::from(p.y)*f64::from(p.y)).sqrt(); } }
    println!("calib sqrt loop {:.3} ms/scan ({acc})", t.elapsed().as_secs_f64() * 1e3 / 20.0);
    let only = std::env::var("ONLY").is_ok();
    let cases: &[(AngleMethod, usize)] = if only { &[(AngleMethod::Exact, 1)] } else { &[(AngleMethod::Exact, 1), (AngleMethod::Exact, 2), (AngleMethod::Fast, 1), (AngleMethod::Fast, 2)] };
    for &(m, th) in cases {
        let pr = Projector::new(&LidarSensor::hdl64e(), ProjectionOptions { angles: m, ..Default::default() }).unwrap().with_threads(th);
        let mut best = f64::MAX;
        for _ in 0..if only {1000} else {200} { let t = Instant::now(); let r = pr.project(&pts, None, None).unwrap(); std::hint::black_box(r); best = best.min(t.elapsed().as_secs_f64()); }
        println!("{m:?} x{th}: min {:.3} ms", best * 1e3);
        let mut best = f64::MAX;
        for _ in 0..100 { let t = Instant::now(); let mut a = 0u64; for p in &pts { if let Some((r, c)) = pr.try_pixel(*p, None) { a += (r + c) as u64; } } std::hint::black_box(a); best = best.min(t.elapsed().as_secs_f64()); }
        println!("  try_pixel only: min {:.3} ms", best * 1e3);
    }
}
#[allow(dead_code)]
fn extra() {}
