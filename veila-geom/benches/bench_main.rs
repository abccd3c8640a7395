use std::hint::black_box;
use std::path::Path;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use veila_geom::{AngleMethod, LidarSensor, ProjectionOptions, Projector};

fn load_scan() -> Vec<Vec3> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti/training/velodyne/000000.bin");
    let bytes = std::fs::read(p).unwrap();
    bytes
        .chunks_exact(16)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[i * 4..i * 4 + 4].try_into().unwrap());
            Vec3::new(f(0), f(1), f(2))
        })
        .collect()
}

fn bench_project(c: &mut Criterion) {
    let pts = load_scan();
    let sensor = LidarSensor::hdl64e();
    let mut g = c.benchmark_group("project_kitti");
    g.throughput(Throughput::Elements(pts.len() as u64));
    for m in [AngleMethod::Exact, AngleMethod::Fast] {
        let pr = Projector::new(&sensor, ProjectionOptions { angles: m, ..Default::default() }).unwrap();
        g.bench_function(format!("{m:?}"), |b| b.iter(|| pr.project(black_box(&pts), None, None).unwrap()));
        let pr2 = pr.clone().with_threads(2);
        g.bench_function(format!("{m:?}_2t"), |b| b.iter(|| pr2.project(black_box(&pts), None, None).unwrap()));
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10).measurement_time(Duration::from_secs(2)).warm_up_time(Duration::from_millis(500));
    targets = bench_project
}
criterion_main!(benches);
