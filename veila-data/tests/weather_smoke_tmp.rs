use std::path::Path;
use veila_data::weather::*;
#[test]
fn smoke() {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/kitti/training/velodyne/000001.bin");
    let cloud = veila_data::scan::read_points(&p).unwrap().cloud;
    let beams = BeamTable::hdl64e();
    for pr in Preset::ALL {
        let t0 = std::time::Instant::now();
        let sim = WeatherSim::new(&pr.weather().with_seed(3), &WeatherConfig::default()).unwrap();
        let t1 = t0.elapsed();
        let out = sim
            .apply_lidar(LidarInput {
                cloud: &cloud,
                ground_mask: None,
                beams: Some(&beams),
            })
            .unwrap();
        println!(
            "{pr}: {:?} {:?} n={} {}",
            t1,
            t0.elapsed(),
            out.cloud.len(),
            serde_json::to_string(&out.records).unwrap()
        );
    }
}
