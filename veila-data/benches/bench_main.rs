use criterion::{criterion_group, criterion_main};

mod io_bench;
mod plot_bench;
mod sim_bench;
mod weather_bench;

criterion_group!(io, io_bench::bench_shard, io_bench::bench_previews);
criterion_group!(
    sim,
    sim_bench::bench_lidar,
    sim_bench::bench_snapshot,
    sim_bench::bench_camera
);
criterion_group!(
    weather,
    weather_bench::bench_lidar_effects,
    weather_bench::bench_fog_table,
    weather_bench::bench_snow_density,
    weather_bench::bench_camera_effects
);
criterion_group!(plot, plot_bench::bench_plots);
criterion_main!(io, sim, weather, plot);
