use std::path::Path;
use veila_data::sim::*;

#[test]
fn scratch_dump() {
    for name in ["straight_road", "junction", "narrow_street"] {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(format!("{name}.toml"));
        let cfg = SceneConfig::from_file(&p).unwrap();
        let t = std::time::Instant::now();
        let out = Path::new("/tmp/simview").join(name);
        let s = simulate_to_dir(&cfg, 0, 1, &out, |_| {}).unwrap();
        eprintln!("{name}: {:?} in {:?}", s.frame_stats[0], t.elapsed());
    }
}
