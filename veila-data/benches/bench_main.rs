use criterion::{Criterion, criterion_group, criterion_main};

mod sim_bench;

fn placeholder(_c: &mut Criterion) {}

criterion_group!(benches, placeholder);
criterion_group!(sim, sim_bench::bench_lidar, sim_bench::bench_snapshot, sim_bench::bench_camera);
criterion_main!(benches, sim);
